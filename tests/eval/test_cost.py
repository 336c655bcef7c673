"""The cost sweep's machinery (`eval.cost`) with the small real stage functions of the pipeline tests."""

from __future__ import annotations

import json
import shutil

import pytest

from eval.cli import main
from eval.cost import CostConfig, apply_knob, run_cost_sweep, sweep_points, write_cost_results
from eval.pipeline import preset
from eval.pipeline.validate import DatasetFolder
from mvgeo.common.errors import InputError
from tests.eval._tiny_stages import TinyStages, make_scene


def _dataset(tmp_path, n=6):
    images = make_scene(tmp_path / "data" / "images", n=n)
    files = {p.stem: p for p in sorted(images.glob("*.png"))}
    names = sorted(files)
    return DatasetFolder(root=tmp_path / "data", train=names[1:], test=names[:1], images=files, clean=files)


def test_sweep_points_change_one_knob_at_a_time():
    base = preset("fast", rounds=1, views=4)
    pts = sweep_points(base, {"splat_iters": (10, 20), "passes": (1,), "views": (2,), "train_views": (3,),
                              "preset": ("default",)})
    assert [p.name for p in pts] == ["base", "splat_iters=10", "splat_iters=20", "passes=1", "views=2",
                                     "train_views=3", "preset=default"]
    assert pts[1].config.splat.iters == 10 and pts[1].config.denoise == base.denoise
    assert pts[3].config.denoise.passes == 1 and pts[3].config.splat == base.splat
    assert pts[4].config.views == 2 and pts[4].config.rounds == 2
    assert pts[5].config == base and pts[5].train_views == 3
    assert pts[6].config.splat.preset == "instantsplat" and pts[6].config.rounds == preset("default").rounds
    assert pts[6].config.denoise == preset("default").denoise and pts[6].config.views == 4
    pt = apply_knob(base, "align_points", 5000)
    assert pt.align.points == 5000 and pt.align.preset == base.align.preset and pt.splat == base.splat
    with pytest.raises(InputError, match="align.points"):  # a ConfigError naming the key
        apply_knob(base, "align_points", 0)
    with pytest.raises(InputError, match="knob"):
        apply_knob(base, "nope", 1)
    with pytest.raises(InputError):
        sweep_points(base, {"splat_iters": ()})


def test_sweep_reuses_stages_and_scores(tmp_path):
    ds = _dataset(tmp_path)
    tiny = TinyStages()
    scored = []

    def score(run_dir, dataset, names):
        scored.append((run_dir.parent.name, len(names)))
        return {"psnr_db": 20.0 + len(names), "ssim": 0.5, "lpips": 0.3, "rot_err_deg": 1.0, "ate": 0.1}

    cfg = CostConfig(base=preset("fast", rounds=1, views=3),
                     grid={"splat_iters": (7,), "passes": (1,), "views": (3,), "train_views": (3, 5)})
    rows = run_cost_sweep(ds, tmp_path / "out", cfg, score=score, stages=tiny.stages())
    names = [r.name for r in rows]
    assert names == ["base", "splat_iters=7", "passes=1", "views=3", "train_views=3", "train_views=5"]
    # Stage reuse through the base point's linked stages: splat_iters re-runs splat+render only,
    # passes re-runs denoise and everything downstream, views adds round 2 only, train_views=5 (all
    # training images) is the base again, train_views=3 a full new run.
    assert tiny.calls["denoise"] == 3 and tiny.calls["refine"] == 1
    assert tiny.calls["align"] == 1 + 1 + 1 + 1  # base, passes, views (round 2), train_views=3
    assert tiny.calls["splat"] == 1 + 1 + 1 + 1 + 1
    by = {r.name: r for r in rows}
    assert by["train_views=3"].psnr_db == 23.0 and by["base"].psnr_db == 25.0
    assert set(by["views=3"].stage_s) >= {"round1/denoise", "round2/refine", "round2/render"}
    assert by["base"].total_s == pytest.approx(sum(by["base"].stage_s.values()))
    # A second run computes nothing: every stage and score is cached.
    tiny2, scored_before = TinyStages(), len(scored)
    rows2 = run_cost_sweep(ds, tmp_path / "out", cfg, score=score, stages=tiny2.stages())
    assert sum(tiny2.calls.values()) == 0 and len(scored) == scored_before
    assert [r.psnr_db for r in rows2] == [r.psnr_db for r in rows]
    json_path, md_path = write_cost_results(tmp_path / "out", rows, title="cost")
    data = json.loads(json_path.read_text())
    assert len(data["points"]) == len(rows)
    md = md_path.read_text()
    assert "splat_iters" in md and "psnr_vs_time.png" in md
    for f in ("psnr_vs_time.png", "pose_vs_time.png", "stage_times.png"):
        assert (tmp_path / "out" / "figures" / f).stat().st_size > 1000


def test_cost_cli_bad_input(tmp_path, capsys):
    ds = _dataset(tmp_path)
    out = str(tmp_path / "out")
    assert main(["cost", str(ds.root / "missing"), "--out", out]) == 2
    assert main(["cost", "llff_like", "--out", out, "--knobs", "nope"]) == 2
    assert "unknown knob" in capsys.readouterr().err
    assert main(["cost", "llff_like", "--out", out, "--grid", "splat_iters=ten"]) == 2
    assert main(["cost", "llff_like", "--out", out, "--grid", "preset=huge"]) == 2
    assert not (tmp_path / "out").exists()  # nothing computed, nothing written


def test_train_views_beyond_the_dataset(tmp_path, caplog, capsys):
    """The default grid's train_views beyond a dataset's training views are left out with a warning (such a
    point would use every view under another count's label); a value given in --grid is refused before any
    compute, naming the dataset's count."""
    from eval.cost import DEFAULT_GRID
    from tests.eval._tiny_stages import tiny_dataset

    ds = tiny_dataset(tmp_path / "data")  # 5 training views
    shutil.copytree(ds.root / "images", ds.root / "clean")
    assert max(DEFAULT_GRID["train_views"]) > 5
    tiny = TinyStages()
    cfg = CostConfig(base=preset("fast", rounds=1, views=4), grid={"train_views": (3, 999)})
    score = lambda rd, ds, names: {"psnr_db": 20.0 + len(names), "ssim": 0.5, "lpips": 0.2,  # noqa: E731
                                   "rot_err_deg": 1.0, "ate": 0.1}
    rows = run_cost_sweep(ds, tmp_path / "out", cfg, score=score, stages=tiny.stages())
    assert [r.name for r in rows] == ["base", "train_views=3"]
    assert "train_views=999 left out of the sweep" in caplog.text
    capsys.readouterr()
    assert main(["cost", str(ds.root), "--out", str(tmp_path / "cli"), "--grid", "train_views=3,9"]) == 2
    err = capsys.readouterr().err
    assert "--grid train_views=9 asks for more training views than the dataset has (5)" in err, err
    assert not (tmp_path / "cli" / "points").exists()
