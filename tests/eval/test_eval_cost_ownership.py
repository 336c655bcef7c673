"""`denoise-gs eval` / `denoise-gs cost` change only files they wrote: results, figures, held-out renders,
cached scores and working-size datasets are committed with records; a file the command did not write, or
one that changed since, stops it with exit code 2 before any run, naming the file, and nothing is changed.
Writes never go through a hard or symbolic link. An error about the output folder met inside a run stops
the evaluation instead of becoming a "failed" row.

The runs use the small real stages of the pipeline tests (`TinyStages`) and a fake scorer."""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import shutil

import numpy as np
import pytest

import eval.evaluate
import eval.methods
from eval.cli import main
from eval.cost import CostConfig, CostPoint, plot_cost, run_cost_sweep, write_cost_results
from eval.evaluate import EvalConfig, EvalTask, evaluate_dataset, run_task
from eval.methods import METHODS
from eval.pipeline import preset
from eval.pipeline.inputs import working_dataset
from eval.pipeline.stage import UnownedOutputError
from eval.results import RunScores, plot_bars, plot_heldout_grid, write_results
from mvgeo.common.imageio import write_image
from mvgeo.common.output import LOCK_NAME
from tests.eval._tiny_stages import TinyStages, tiny_dataset

SCENE = "ds"
METHOD_ARGS = ["--methods", "instantsplat", "--seeds", "1", "--preset", "fast", "--max-size", "0"]


class Harness:
    """Tiny stages in place of the product's and a scorer that counts its calls."""

    def __init__(self, monkeypatch):
        self.tiny = TinyStages()
        self.scored = 0
        monkeypatch.setattr(eval.methods, "product_stages", self.tiny.stages)
        monkeypatch.setattr(eval.evaluate, "read_gaussian_ply", lambda path, device: path)
        monkeypatch.setattr(eval.evaluate, "_score_scene", self.score)

    def score(self, model, gt, est_train, dataset, config, est_cameras=(), renders_out=None):
        self.scored += 1
        if renders_out is not None:
            renders_out.update({n: np.full((40, 48, 3), 0.25 * self.scored, np.float32) for n in dataset.test})
        return {n: {"psnr_db": 20.0, "ssim": 0.5, "lpips": 0.3} for n in dataset.test}, \
            {"rot_err_deg": 1.0, "ate": 0.1}

    def work(self) -> int:
        """Stage calls and scorings so far."""
        return sum(self.tiny.calls.values()) + self.scored


@pytest.fixture()
def root(tmp_path):
    """A dataset folder `ds/` (clean = noisy images) for the command line."""
    ds = tiny_dataset(tmp_path / SCENE).root
    shutil.copytree(ds / "images", ds / "clean")
    return ds


def _eval(root, out, *extra) -> int:
    return main(["eval", str(root), "--out", str(out), *METHOD_ARGS, *extra])


def _snapshot(folder) -> dict[str, bytes]:
    """Every file's bytes (lock files, which hold the holder's pid, left out)."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not p.is_symlink() and p.name != LOCK_NAME}


# ----------------------------------------------------------------- 1. user files stop eval and cost up front
def _append_to_results(out, outside):
    with open(out / "results.md", "a") as f:
        f.write("my notes\n")
    return out / "results.md"


def _file_in_figures(out, outside):
    (out / "figures" / "mine.txt").write_text("mine")
    return out / "figures" / "mine.txt"


def _edited_render(out, outside):
    render = out / "heldout" / SCENE / "instantsplat" / "seed0" / "view_000.png"
    write_image(render, np.zeros((40, 48, 3), np.float32))
    return render


def _render_linked_to_a_user_file(out, outside):
    render = out / "heldout" / SCENE / "instantsplat" / "seed0" / "view_000.png"
    render.unlink()
    render.symlink_to(outside)
    return render


def _file_in_a_run_folder(out, outside):
    notes = out / "runs" / SCENE / "seed0" / "instantsplat" / "round1" / "renders" / "notes.txt"
    notes.write_text("mine")
    return notes


@pytest.mark.parametrize("tamper", [_append_to_results, _file_in_figures, _edited_render,
                                    _render_linked_to_a_user_file, _file_in_a_run_folder])
def test_eval_refuses_files_it_did_not_write_before_any_run(root, tmp_path, monkeypatch, capsys, tamper):
    h = Harness(monkeypatch)
    out, outside = tmp_path / "ev1", tmp_path / "user.png"
    write_image(outside, np.ones((40, 48, 3), np.float32))
    assert _eval(root, out) == 0, capsys.readouterr().err
    assert (out / "stages" / "results.json").is_file()
    assert (out / "heldout" / "stages" / f"{SCENE}.instantsplat.seed0.json").is_file()
    user_file = tamper(out, outside)
    mine = user_file.read_bytes()
    before, outside_before, work = _snapshot(out), outside.read_bytes(), h.work()
    capsys.readouterr()
    assert _eval(root, out) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and str(user_file.name) in err and "fix:" in err
    assert h.work() == work  # refused before any stage or scoring
    assert user_file.read_bytes() == mine and outside.read_bytes() == outside_before
    assert _snapshot(out) == before  # results, renders and runs as they were
    assert not [p for p in out.rglob(".*work-*")]


def test_eval_rewrites_its_own_files_and_never_writes_through_links(root, tmp_path, monkeypatch, capsys):
    h = Harness(monkeypatch)
    out = tmp_path / "ev1"
    assert _eval(root, out) == 0, capsys.readouterr().err
    figure = out / "figures" / "psnr_db.png"
    render = out / "heldout" / SCENE / "instantsplat" / "seed0" / "view_000.png"
    os.link(figure, tmp_path / "figure_link.png")
    os.link(render, tmp_path / "render_link.png")
    kept = {p: p.read_bytes() for p in (tmp_path / "figure_link.png", tmp_path / "render_link.png")}
    assert _eval(root, out) == 0, capsys.readouterr().err  # its own files, unchanged: replaced
    assert h.scored == 2
    assert render.read_bytes() != kept[tmp_path / "render_link.png"]  # the new render (another fake image) ...
    assert all(p.read_bytes() == b for p, b in kept.items())  # ... by a rename: the links keep the old bytes
    assert not os.path.samefile(render, tmp_path / "render_link.png")


def test_cost_refuses_files_it_did_not_write_before_any_point(tmp_path):
    ds = tiny_dataset(tmp_path / "data")
    tiny, scored = TinyStages(), []

    def score(run_dir, dataset, names):
        scored.append(run_dir)
        return {"psnr_db": 20.0, "ssim": 0.5, "lpips": 0.3, "rot_err_deg": 1.0, "ate": 0.1}

    cfg = CostConfig(base=preset("fast", rounds=1, views=3), grid={"splat_iters": (7,)})
    out = tmp_path / "co1"
    rows = run_cost_sweep(ds, out, cfg, score=score, stages=tiny.stages())
    write_cost_results(out, rows, title="cost")
    assert (out / "stages" / "results.json").is_file() and (out / "points" / "base" / "stages" / "score.json").is_file()
    calls = sum(tiny.calls.values())
    for user_file, edit in ((out / "results.md", "notes"), (out / "figures" / "mine.txt", "mine"),
                            (out / "points" / "base" / "score.json", "not json")):
        existed = user_file.is_file()
        original = user_file.read_bytes() if existed else None
        user_file.write_text(edit)
        with pytest.raises(UnownedOutputError, match=user_file.name):
            run_cost_sweep(ds, out, cfg, score=score, stages=tiny.stages())
        if user_file.name != "score.json":
            with pytest.raises(UnownedOutputError, match=user_file.name):
                write_cost_results(out, rows, title="cost")
        assert user_file.read_text() == edit and sum(tiny.calls.values()) == calls and len(scored) == 2
        if existed:
            user_file.write_bytes(original)
        else:
            user_file.unlink()
    again = run_cost_sweep(ds, out, cfg, score=score, stages=tiny.stages())  # all its own again: reused
    assert [(r.name, r.psnr_db) for r in again] == [(r.name, r.psnr_db) for r in rows]
    assert sum(tiny.calls.values()) == calls and len(scored) == 2


def test_cost_cli_refuses_a_user_score_file_that_is_not_json(root, tmp_path, capsys):
    from eval.pipeline.run import RUN_COMMAND
    from mvgeo.common.output import prepare_output, resumable_output_dir, write_manifest

    out = tmp_path / "co1"
    with resumable_output_dir(prepare_output(out, command="denoise-gs cost", inputs=[root], resume=True)):
        pass  # a cost folder, as a finished sweep leaves it
    (out / "points" / "base").mkdir(parents=True)
    write_manifest(out / "points" / "base", RUN_COMMAND, record_files=False)  # the base point's run folder
    (out / "points" / "base" / "score.json").write_text("{not json")
    assert main(["cost", str(root), "--out", str(out), "--grid", "splat_iters=5", "--knobs", "splat_iters",
                 "--views", "3"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "points/base/score.json (not written" in err
    assert (out / "points" / "base" / "score.json").read_text() == "{not json"
    assert not (out / "points" / "base" / "round1").exists()  # nothing ran


def test_a_cached_score_that_is_not_json_is_a_typed_error(tmp_path):
    from eval.cost import _cached_scores
    from mvgeo.common.errors import InputError

    cache = tmp_path / "score.json"
    cache.write_text("{not json")
    with pytest.raises(InputError, match="score.json.*cannot be read"):
        _cached_scores(cache, {"render": "k"})
    cache.write_text("[1, 2]")
    with pytest.raises(InputError, match="not an object"):
        _cached_scores(cache, {"render": "k"})


# ----------------------------------------------------------------- 2. figures replace files, never write into them
def _rows(psnr: float) -> list[RunScores]:
    return [RunScores(SCENE, "a", 0, psnr, 0.5, 0.3), RunScores(SCENE, "b", 0, psnr + 1, 0.6, 0.2)]


def test_figures_replace_hard_and_symbolic_links(tmp_path):
    user = tmp_path / "user.png"
    user.write_bytes(b"the user's picture")

    def check(draw, path):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"old figure")
        os.link(path, tmp_path / f"{path.name}.link")
        draw(path)
        assert (tmp_path / f"{path.name}.link").read_bytes() == b"old figure"  # a hard link keeps its bytes
        assert path.read_bytes().startswith(b"\x89PNG")
        path.unlink()
        path.symlink_to(user)
        draw(path)
        assert user.read_bytes() == b"the user's picture" and not path.is_symlink()  # the link was replaced
        assert not [p for p in path.parent.iterdir() if ".tmp-" in p.name]

    check(lambda p: plot_bars(_rows(20.0), p), tmp_path / "bars" / "psnr_db.png")
    folder = tmp_path / "heldout" / SCENE
    for part in ("_clean", "a/seed0"):
        write_image(folder / part / "view_000.png", np.full((8, 8, 3), 0.5, np.float32))
    check(lambda p: plot_heldout_grid(folder, p), tmp_path / "grid" / "heldout.png")
    point = CostPoint("base", "base", None, {"round1/splat": 1.0}, 1.0, 20.0, 0.5, 0.3, 1.0, 0.1)
    point2 = dataclasses.replace(point, name="splat_iters=7", knob="splat_iters", value=7)

    def cost_figures(p):
        assert p in plot_cost([point, point2], p.parent)

    check(cost_figures, tmp_path / "cost" / "stage_times.png")


def test_results_committed_with_a_record_replace_only_their_own_files(tmp_path):
    out = tmp_path / "out"
    write_results(out, _rows(20.0), title="t")
    os.link(out / "figures" / "psnr_db.png", tmp_path / "link.png")
    old = (tmp_path / "link.png").read_bytes()
    write_results(out, _rows(25.0), title="t")  # its own files: replaced by renames
    assert (tmp_path / "link.png").read_bytes() == old != (out / "figures" / "psnr_db.png").read_bytes()
    assert "25.00" in (out / "results.md").read_text()
    (out / "results.md").write_text("edited")
    results = (out / "results.json").read_bytes()
    with pytest.raises(UnownedOutputError, match="results.md"):
        write_results(out, _rows(30.0), title="t")
    assert (out / "results.md").read_text() == "edited" and (out / "results.json").read_bytes() == results
    assert json.loads(results)["runs"][0]["psnr_db"] == 25.0


# ----------------------------------------------------------------- 3. output-folder errors stop the evaluation
def _task(dataset, out) -> EvalTask:
    cfg = EvalConfig(methods=("instantsplat",), seeds=1, preset="fast")
    inputs = eval.evaluate.copy_train_inputs(dataset, out / "inputs" / "s")
    return EvalTask("s", METHODS["instantsplat"], 0, dataset, preset("fast", views=3), inputs, out, cfg)


def test_a_user_file_in_a_run_folder_stops_run_task_with_a_picklable_error(tmp_path, monkeypatch):
    h = Harness(monkeypatch)
    dataset = tiny_dataset(tmp_path / "data")
    task = _task(dataset, tmp_path / "out")
    assert not run_task(task).error
    notes = tmp_path / "out" / "runs" / "s" / "seed0" / "instantsplat" / "round1" / "renders" / "notes.txt"
    notes.write_text("mine")
    with pytest.raises(UnownedOutputError, match="notes.txt") as info:  # not a "failed" row
        run_task(task)
    again = pickle.loads(pickle.dumps(info.value))  # as a Ray task returns it
    assert isinstance(again, UnownedOutputError) and str(again) == str(info.value) and again.paths
    assert notes.read_text() == "mine" and h.scored == 1


def test_a_run_folder_that_is_not_a_run_stops_the_evaluation(tmp_path, monkeypatch):
    h = Harness(monkeypatch)
    dataset = tiny_dataset(tmp_path / "data")
    out = tmp_path / "out"
    folder = out / "runs" / "s" / "seed0" / "instantsplat"
    folder.mkdir(parents=True)
    (folder / "mine.txt").write_text("mine")
    rows = []
    with pytest.raises(eval.evaluate.InputError, match="did not write"):
        evaluate_dataset(dataset, out, EvalConfig(methods=("n2v_round1", "instantsplat"), seeds=1, preset="fast"),
                         scene="s", on_row=rows.append)
    assert rows == [] and h.work() == 0 and (folder / "mine.txt").read_text() == "mine"
    # Met inside a run (the up-front check bypassed): it stops the evaluation too, no "failed" row.
    with pytest.raises(eval.evaluate.InputError, match="did not write"):
        run_task(_task(dataset, out))


def test_a_method_failure_is_still_a_failed_row(tmp_path, monkeypatch):
    from mvgeo.common.errors import InputError

    h = Harness(monkeypatch)

    def align(ctx):
        raise InputError("no usable pairs", path=ctx.inputs["images"])  # names a file inside the run folder

    monkeypatch.setattr(h.tiny, "align", align)
    row = run_task(_task(tiny_dataset(tmp_path / "data"), tmp_path / "out"))
    assert row.error.startswith("InputError: ") and "no usable pairs" in row.error


# ----------------------------------------------------------------- 4. working-size datasets
def test_working_dataset_refuses_a_user_folder_at_its_path(tmp_path):
    root = tiny_dataset(tmp_path / SCENE).root
    shutil.copytree(root / "images", root / "clean")
    out = tmp_path / "ev1"
    mine = out / "data" / f"{SCENE}_max32" / "notes.txt"
    mine.parent.mkdir(parents=True)
    mine.write_text("mine")
    with pytest.raises(UnownedOutputError, match="notes.txt"):
        working_dataset(root, out, 32)
    assert mine.read_text() == "mine" and sorted(os.listdir(out / "data")) == [f"{SCENE}_max32"]
    mine.unlink()
    small = working_dataset(root, out, 32)  # an empty folder holds nothing to lose
    assert (small / "split.json").is_file() and (out / "data" / "stages" / f"{SCENE}_max32.json").is_file()
    stamp = (small / "split.json").stat().st_mtime_ns
    assert working_dataset(root, out, 32) == small and (small / "split.json").stat().st_mtime_ns == stamp  # reused
    write_image(small / "images" / "view_001.png", np.zeros((27, 32, 3), np.float32))  # changed by the user
    with pytest.raises(UnownedOutputError, match="view_001.png"):
        working_dataset(root, out, 32)
    assert not [p for p in (out / "data").iterdir() if p.name.startswith(".")]


def _open_eval_folder(root, out):
    """`out` opened as `denoise-gs eval` opens it (its manifest, the scene's training photos in inputs/),
    before any of its runs."""
    from eval.evaluate import copy_train_inputs
    from eval.pipeline import validate_dataset_folder
    from mvgeo.common.output import prepare_output, resumable_output_dir

    dataset = validate_dataset_folder(root)
    with resumable_output_dir(prepare_output(out, command="denoise-gs eval", inputs=[root], resume=True)) as folder:
        copy_train_inputs(dataset, folder / "inputs" / dataset.root.name)


def test_eval_cli_refuses_a_user_folder_at_the_working_dataset(root, tmp_path, capsys):
    out = tmp_path / "ev1"
    _open_eval_folder(root, out)
    mine = out / "data" / f"{SCENE}_max32" / "notes.txt"
    mine.parent.mkdir(parents=True)
    mine.write_text("mine")
    assert _eval(root, out, "--max-size", "32") == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "notes.txt" in err
    assert mine.read_text() == "mine" and sorted(os.listdir(out / "data")) == [f"{SCENE}_max32"]


def test_eval_resumes_a_folder_with_a_run_in_it(root, tmp_path, monkeypatch, capsys):
    """An evaluation folder with a `denoise-gs run` made into one of its run folders (same settings): the
    evaluation reuses that run and only scores it."""
    from eval.pipeline import run_pipeline

    h = Harness(monkeypatch)
    out = tmp_path / "ev1"
    _open_eval_folder(root, out)
    config = METHODS["instantsplat"].pipeline_config(dataclasses.replace(
        preset("fast", views=5), max_size=None,
        align=dataclasses.replace(preset("fast").align, max_focal_log_std=eval.evaluate.FOCAL_PRIOR_OK)))
    run_pipeline(out / "inputs" / SCENE, out / "runs" / SCENE / "seed0" / "instantsplat", config,
                 stages=METHODS["instantsplat"].stages(None))
    calls = dict(h.tiny.calls)
    assert _eval(root, out) == 0, capsys.readouterr().err
    assert dict(h.tiny.calls) == calls and h.scored == 1  # the run was reused, then scored
