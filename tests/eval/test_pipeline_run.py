"""The pipeline framework end to end with small real stage functions (tests/eval/_tiny_stages.py)."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from eval.pipeline import PipelineConfig, preset, run_pipeline, stage_seed
from eval.pipeline.lock import LOCK_NAME, output_lock
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import write_image
from mvgeo.common.output import MANIFEST_NAME
from mvgeo.sparse_model import read_sparse_model
from tests.eval._tiny_stages import TinyStages, make_scene

ALL_STAGES = {"denoise", "align", "splat", "render", "select", "refine"}


def _cfg(**kw) -> PipelineConfig:
    # The run's mechanics without the fuse extension (tests/eval/test_fuse_stage.py covers it).
    return dataclasses.replace(preset("fast", views=3, **kw), fuse_noisy_splat=False)


def _leftovers(out):
    return [p for p in out.rglob(".*") if p.name not in (LOCK_NAME, MANIFEST_NAME)]


@pytest.fixture()
def scene(tmp_path):
    return make_scene(tmp_path / "images", n=5)


def test_two_rounds_layout_report_and_selection(tmp_path, scene):
    tiny = TinyStages()
    out = tmp_path / "out"
    res = run_pipeline(scene, out, _cfg(rounds=2), stages=tiny.stages())
    assert dict(tiny.calls) == {"denoise": 1, "align": 2, "splat": 2, "render": 2, "select": 1, "refine": 1}
    for r in (1, 2):
        rd = out / f"round{r}"
        assert (rd / "denoised").is_dir() and (rd / "renders").is_dir() and (rd / "point_cloud.ply").is_file()
        assert read_sparse_model(rd / "sparse" / "0").names
    # Round 1 covers every view; round 2 only the K selected ones.
    assert len(list((out / "round1" / "denoised").glob("*.png"))) == 5
    selected = json.loads((out / "round2" / "selection.json").read_text())["names"]
    assert len(selected) == 3
    assert sorted(p.stem for p in (out / "round2" / "denoised").glob("*.png")) == selected
    report = json.loads(res.report_json.read_text())
    assert report["selected_views"] == {"round2": selected}
    assert {s["stage"] for s in report["stages"]} == ALL_STAGES
    assert set(report["timings_s_this_run"]) >= {"round1/denoise", "round2/refine", "total"}
    assert report["settings"]["views"] == 3
    md = res.report_md.read_text()
    assert "contact_round1.png" in md and "contact_round2.png" in md
    sheet = out / "report_files" / "contact_round2.png"
    assert sheet.is_file() and sheet.stat().st_size > 0
    # The run's own checks: each round's renders against its denoised photos, and its cameras plotted.
    assert "## Quality" in md and "cameras_round1.png" in md and "cameras_round2.png" in md
    assert sorted(report["quality"]["round2"]["splat"]["fit_psnr_db"]) == sorted(selected)
    assert [report["quality"][f"round{r}"]["denoise"]["kind"] for r in (1, 2)] == ["training", "fine-tuning"]
    assert report["camera_plots"] == {"round1": "report_files/cameras_round1.png",
                                      "round2": "report_files/cameras_round2.png"}
    assert (out / "report_files" / "cameras_round2.png").stat().st_size > 0
    assert not _leftovers(out)
    assert not (out / LOCK_NAME).exists()


@pytest.mark.parametrize("stop", [True, False])
def test_a_round_whose_refine_kept_the_previous_network_ends_the_loop(tmp_path, scene, stop):
    tiny = TinyStages()
    tiny.refine_keeps_previous = True
    out = tmp_path / "out"
    res = run_pipeline(scene, out, dataclasses.replace(_cfg(rounds=3), stop_when_unrefined=stop), stages=tiny.stages())
    report = json.loads(res.report_json.read_text())
    if not stop:  # the paper's loop: every round runs whatever the guard says
        assert [r.index for r in res.rounds] == [1, 2, 3] and res.stopped is None and report["stopped"] is None
        assert tiny.calls["splat"] == 3
        return
    # Round 2 ran select and refine, then stopped: no second alignment or splat; round 1 is the result.
    assert dict(tiny.calls) == {"denoise": 1, "align": 1, "splat": 1, "render": 1, "select": 1, "refine": 1}
    assert [r.index for r in res.rounds] == [1] and res.stopped.index == 2
    assert set(res.stopped.stages) == {"select", "refine"} and "0.012500 before, 0.013100 after" in res.stopped.reason
    assert report["result_round"] == 1 and report["stopped"]["round"] == 2
    assert {(s["round"], s["stage"]) for s in report["stages"]} >= {(2, "select"), (2, "refine")}  # its time counted
    assert "round 2 stopped after its refine" in res.report_md.read_text()
    assert not (out / "round2" / "point_cloud.ply").exists() and not (out / "round3").exists()
    again = run_pipeline(scene, out, dataclasses.replace(_cfg(rounds=3), stop_when_unrefined=True),
                         stages=tiny.stages())  # resumed: the same decision from the recorded refine
    assert tiny.calls["refine"] == 1 and again.stopped.index == 2 and [r.index for r in again.rounds] == [1]


def test_photos_passed_through_by_round_1_end_the_loop_there(tmp_path, scene):
    """Round 1's denoise stage wrote no network (the photos read as clean): round 2 has nothing to fine-tune,
    so it is not run, whatever `stop_when_unrefined` says; round 1's reconstruction is the result."""
    tiny = TinyStages()
    tiny.passes_through = True
    out = tmp_path / "out"
    cfg = dataclasses.replace(_cfg(rounds=3), stop_when_unrefined=False)
    res = run_pipeline(scene, out, cfg, stages=tiny.stages())
    assert dict(tiny.calls) == {"denoise": 1, "align": 1, "splat": 1, "render": 1}
    assert [r.index for r in res.rounds] == [1] and res.stopped.index == 2 and res.stopped.stages == {}
    assert "round 2 not run" in res.stopped.reason
    assert not (out / "round1" / "n2v_model.pt").exists() and not (out / "round2").exists()
    report = json.loads(res.report_json.read_text())
    assert report["result_round"] == 1 and report["stopped"]["round"] == 2
    md = res.report_md.read_text()
    assert "round 2 not run" in md and "no network was trained" in md
    again = run_pipeline(scene, out, cfg, stages=tiny.stages())  # resumed: every stage skipped
    assert tiny.calls["denoise"] == 1 and again.stopped.index == 2 and not _leftovers(out)


def test_a_refine_that_improved_goes_on(tmp_path, scene):
    tiny = TinyStages()
    res = run_pipeline(scene, tmp_path / "out", dataclasses.replace(_cfg(rounds=2), stop_when_unrefined=True),
                       stages=tiny.stages())
    assert [r.index for r in res.rounds] == [1, 2] and res.stopped is None


def test_later_rounds_refine_at_round_1s_stride_and_noise_model(tmp_path, scene):
    """Every round fine-tunes round 1's network, which learned the photos at round 1's pixel-shuffle stride:
    the refine stage takes round 1's stride and noise model (its denoise summary) instead of measuring them
    again on its K selected views, which can read otherwise (below)."""
    import cv2

    from denoise.pixel_shuffle import stride_for

    # Noise correlated between neighbouring pixels at a level that differs from photo to photo: all 12 photos
    # read stride 1, the 6 noisiest (the sharpest by the Laplacian) stride 2.
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.random((192, 256, 3)).astype(np.float32), (0, 0), 6) * 0.6 + 0.2
    photos = []
    for level in np.linspace(4, 12, 12) / 255:
        n = cv2.GaussianBlur(rng.standard_normal(base.shape).astype(np.float32), (0, 0), 0.7)
        photos.append(np.clip(base + n * (level / n.std()), 0, 1))
    assert stride_for(photos, 0).stride == 1 and stride_for(photos[6:], 0, hint=False).stride == 2

    tiny = TinyStages()
    seen = []

    def denoise(ctx):
        return {**tiny.denoise(ctx), "pd_stride": 2, "noise_level_luma_255": 6.5}

    def refine(ctx):
        seen.append((ctx.settings.pd_stride, ctx.settings.noise_model))
        return tiny.refine(ctx)

    stages = dataclasses.replace(tiny.stages(), denoise=denoise, refine=refine)
    run_pipeline(scene, tmp_path / "out", _cfg(rounds=3), stages=stages)
    assert seen == [(2, "luma"), (2, "luma")]
    # A stride and noise model the user set are kept (round 1 used them too).
    seen.clear()
    cfg = _cfg(rounds=2)
    cfg = dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, pd_stride=3, noise_model="auto"))
    run_pipeline(scene, tmp_path / "out2", cfg, stages=stages)
    assert seen == [(3, "auto")]


def test_rerun_skips_complete_stages(tmp_path, scene):
    tiny = TinyStages()
    out = tmp_path / "out"
    run_pipeline(scene, out, _cfg(), stages=tiny.stages())
    first = dict(tiny.calls)
    res = run_pipeline(scene, out, _cfg(), stages=tiny.stages())
    assert dict(tiny.calls) == first  # nothing ran again
    assert all(s.skipped for r in res.rounds for s in r.stages.values())
    assert res.timings_s == {"total": 0.0}
    # force re-runs everything
    run_pipeline(scene, out, _cfg(), stages=tiny.stages(), force=True)
    assert all(tiny.calls[k] == 2 * first[k] for k in first)


def test_setting_change_reruns_only_what_it_affects(tmp_path, scene):
    tiny = TinyStages()
    out = tmp_path / "out"
    cfg = _cfg(rounds=1)
    run_pipeline(scene, out, cfg, stages=tiny.stages())
    changed = PipelineConfig(views=cfg.views, rounds=1, denoise=cfg.denoise, align=cfg.align,
                             splat=type(cfg.splat)(preset=cfg.splat.preset, iters=123))
    run_pipeline(scene, out, changed, stages=tiny.stages())
    assert dict(tiny.calls) == {"denoise": 1, "align": 1, "splat": 2, "render": 2}


def test_input_change_reruns_from_the_start(tmp_path, scene):
    tiny = TinyStages()
    out = tmp_path / "out"
    run_pipeline(scene, out, _cfg(rounds=1), stages=tiny.stages())
    write_image(scene / "view_002.png", np.full((40, 48, 3), 0.5, np.float32))
    run_pipeline(scene, out, _cfg(rounds=1), stages=tiny.stages())
    # denoise sees new content; align's key chains denoise's key, and so on down.
    assert dict(tiny.calls) == {"denoise": 2, "align": 2, "splat": 2, "render": 2}
    # A non-image file in the input folder changes nothing.
    (scene / "notes.txt").write_text("hello")
    run_pipeline(scene, out, _cfg(rounds=1), stages=tiny.stages())
    assert tiny.calls["denoise"] == 2


@pytest.mark.parametrize("stage", ["denoise", "splat"])
def test_interrupted_run_resumes(tmp_path, scene, stage):
    tiny = TinyStages()
    out = tmp_path / "out"
    run_pipeline(scene, out, _cfg(rounds=1), stages=tiny.stages())
    baseline = dict(tiny.calls)
    # Change the seed so every stage must re-run, then interrupt mid-stage.
    tiny.fail_next.add(stage)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(scene, out, _cfg(rounds=2, seed=7), stages=tiny.stages())
    rd = out / "round1"
    # The interrupted stage's outputs and record are the previous run's (its key is not this run's), no
    # temp folders remain, the previous report was withdrawn, and the lock is released.
    assert json.loads((rd / "stages" / f"{stage}.json").read_text())["seed"] == stage_seed(0, 1, stage)
    assert not (out / "report.json").exists() and not (out / "report.md").exists()
    assert not _leftovers(out) and not (out / LOCK_NAME).exists()
    calls_before = dict(tiny.calls)
    run_pipeline(scene, out, _cfg(rounds=2, seed=7), stages=tiny.stages())
    # Stages that completed before the interruption are not repeated.
    if stage == "splat":
        assert tiny.calls["denoise"] == calls_before["denoise"] == baseline["denoise"] + 1
        assert tiny.calls["align"] == calls_before["align"] + 1  # round 2 only
    assert tiny.calls[stage] == calls_before[stage] + (1 if stage == "denoise" else 2)
    assert (out / "round2" / "renders").is_dir()


def test_bad_inputs_fail_before_any_stage(tmp_path, scene):
    tiny = TinyStages()
    out = tmp_path / "out"
    with pytest.raises(InputError, match="--views 12"):
        run_pipeline(scene, out, preset("fast", views=12, rounds=2), stages=tiny.stages())
    # With one round there is no selection, so K > N is fine.
    with pytest.raises(InputError, match="does not exist"):
        run_pipeline(tmp_path / "nope", out, _cfg(), stages=tiny.stages())
    (scene / "view_001.png").write_bytes(b"garbage")
    with pytest.raises(InputError, match="view_001.png"):
        run_pipeline(scene, out, _cfg(), stages=tiny.stages())
    assert not tiny.calls and not out.exists()


def test_fewer_images_than_views_ok_for_one_round(tmp_path, scene):
    tiny = TinyStages()
    run_pipeline(scene, tmp_path / "out", preset("fast", views=12, rounds=1), stages=tiny.stages())
    assert tiny.calls["render"] == 1


def test_duplicate_stems_and_tiny_images(tmp_path, scene):
    shutil.copy(scene / "view_000.png", scene / "view_000.jpg")
    with pytest.raises(InputError, match="share the name"):
        run_pipeline(scene, tmp_path / "out", _cfg(), stages=TinyStages().stages())
    small = tmp_path / "small"
    small.mkdir()
    for i in range(3):
        write_image(small / f"{i}.png", np.zeros((20, 20, 3), np.float32))
    with pytest.raises(InputError, match="32 px"):
        run_pipeline(small, tmp_path / "out2", _cfg(), stages=TinyStages().stages())


def test_live_lock_refuses_second_run(tmp_path, scene):
    out = tmp_path / "out"
    out.mkdir()
    with output_lock(out), pytest.raises(InputError, match="another run"):  # a live holder
        run_pipeline(scene, out, _cfg(), stages=TinyStages().stages())
    (out / LOCK_NAME).write_text("999999999")  # a lock file nobody holds (its owner died) is taken over
    run_pipeline(scene, out, _cfg(rounds=1), stages=TinyStages().stages())


@pytest.mark.slow  # real N2V and splat training (few steps); minutes on a loaded 2-core machine
def test_product_stages_except_alignment(tmp_path):
    """The product's denoise, splat, render, select and refine stages with the real `denoise` and
    `splat` packages (a handful of steps); alignment from the tiny set (a fixed rig and random points),
    because `mvgeo.align` is tested in its own package."""
    import dataclasses

    from denoise.model import load_checkpoint
    from eval.pipeline import DenoiseSettings, SplatSettings, product_stages
    from splat.ply import read_gaussian_ply

    scene = make_scene(tmp_path / "images", n=5, size_wh=(64, 48))
    tiny = TinyStages()
    real = product_stages()
    stages = dataclasses.replace(real, align=tiny.align)
    # `fast` runs one round unless asked for two. stop_when_unrefined off: 3 fine-tuning steps do not lower
    # the blind-spot loss measurably, and the preset would stop after round 2's refine; this test runs round
    # 2's stages to the end.
    cfg = dataclasses.replace(preset("fast", views=3, rounds=2), fuse_noisy_splat=False, stop_when_unrefined=False,
                              denoise=DenoiseSettings(n2v_preset="fast", n2v_steps=8, passes=1, round2_steps=3),
                              splat=SplatSettings(preset="quick", iters=5))
    res = run_pipeline(scene, tmp_path / "out", cfg, stages=stages)
    r1, r2 = res.rounds
    assert r1.stages["denoise"].summary["train"]["loss"]["count"] == 8
    selected = r2.stages["select"].summary["selected"]
    assert len(selected) == 3 and r2.stages["select"].summary["method"] == "kmeans+laplacian"
    assert sorted(p.stem for p in (r2.dir / "denoised").glob("*.png")) == sorted(selected)
    # Round 2 fine-tunes the round-1 UNet: its loss history continues round 1's. The network it keeps is the
    # fine-tuned one (11 steps of history) or, when the guard reverted it, round 1's (8).
    from eval.pipeline.summaries import RefineSummary

    reverted, _ = RefineSummary.from_json(r2.stages["refine"].summary).kept_previous()
    steps = 8 if reverted else 11
    assert r2.stages["refine"].summary["train"]["loss"]["count"] == steps
    assert len(load_checkpoint(r2.dir / "n2v_model.pt").history) == steps
    # The splat stage wrote a readable 3DGS PLY and the optimised poses; renders match the views.
    assert read_gaussian_ply(r2.dir / "point_cloud.ply").means.shape[0] > 0
    assert read_sparse_model(r2.dir / "sparse" / "0").names == [f"{n}.png" for n in sorted(selected)]
    assert sorted(p.stem for p in (r2.dir / "renders").glob("*.png")) == sorted(selected)


def test_changed_component_default_reruns_its_stage(tmp_path, scene, monkeypatch):
    # Stage keys hash the *resolved* component configs: a changed preset default (same preset name)
    # must re-run the stage that uses it, and only from there on.
    import dataclasses

    import splat.train

    tiny = TinyStages()
    out = tmp_path / "out"
    run_pipeline(scene, out, _cfg(rounds=1), stages=tiny.stages())
    used = _cfg(rounds=1).splat.preset
    shipped = splat.train.TRAIN_PRESETS[used]
    monkeypatch.setitem(splat.train.TRAIN_PRESETS, used, dataclasses.replace(shipped, iters=shipped.iters + 1))
    tiny2 = TinyStages()
    run_pipeline(scene, out, _cfg(rounds=1), stages=tiny2.stages())
    assert dict(tiny2.calls) == {"splat": 1, "render": 1}
