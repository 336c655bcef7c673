"""A resumed run changes only files it wrote: files added to, or changed in, a stage's outputs or the published
result (`scene.splat`, `view/`, `cameras/`, the report) stop it with exit code 2 and nothing changed; a run that
recomputes a stage withdraws the previous published result first; `copy_train_inputs` removes only its own links.

The stages are the small real ones of `tests/eval/_tiny_stages.py`, with an export stage that writes the
published files from the last round's point cloud and cameras.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest

import eval.pipeline.run
from eval.cli import main
from eval.evaluate import copy_train_inputs
from eval.pipeline import PipelineStages, StageContext, preset, run_pipeline, stage_seed
from eval.pipeline.stage import UnownedOutputError
from mvgeo.common.errors import InputError
from mvgeo.sparse_model import read_sparse_model, write_sparse_model
from tests.eval._tiny_stages import TinyStages, make_scene, tiny_dataset

#: What the run publishes at the top of its folder (export and report).
PUBLISHED = ("scene.splat", "view", "cameras", "report.json", "report.md", "report_files")


def export(ctx: StageContext) -> dict[str, object]:
    """The export stage's files from the tiny stages' outputs: the point cloud as `scene.splat`, a page in
    `view/`, and the cameras (COLMAP text) in `cameras/working/` and `cameras/input/`."""
    ply = Path(ctx.inputs["scene"]).read_bytes()
    (ctx.work_dir / "scene.splat").write_bytes(ply)
    (ctx.work_dir / "view").mkdir()
    (ctx.work_dir / "view" / "index.html").write_text(f"<html>{len(ply)} bytes</html>\n")
    sparse = read_sparse_model(Path(ctx.inputs["sparse"]) / "0")
    for size in ("working", "input"):
        write_sparse_model(ctx.work_dir / "cameras" / size, sparse, binary=False)
    return {"num_gaussians": ply.count(b"\n")}


def _stages(tiny: TinyStages) -> PipelineStages:
    return dataclasses.replace(tiny.stages(), export=export)


def _cfg(**kw):
    return dataclasses.replace(preset("fast", views=3, **kw), fuse_noisy_splat=False)


def _tree(out: Path) -> dict[str, bytes]:
    """Every file under `out` (hidden ones included) by relative path, with its bytes."""
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """(photos, a finished one-round run with export); each test works on a copy."""
    root = tmp_path_factory.mktemp("owned")
    scene = make_scene(root / "images", n=5)
    run_pipeline(scene, root / "ref", _cfg(rounds=1), stages=_stages(TinyStages()))
    assert all((root / "ref" / p).exists() for p in PUBLISHED)
    return scene, root / "ref"


def _copy(finished, tmp_path) -> Path:
    out = tmp_path / "run_out"
    shutil.copytree(finished[1], out, symlinks=True)
    return out


def _append(path: Path) -> None:
    path.write_bytes(path.read_bytes() + b"# mine\n")


#: What the user does in the finished run folder -> the file the refusal names.
USER_CHANGES = {
    "file in inputs/": (lambda out: (out / "inputs" / "my_extra.txt").write_text("m\n"), "inputs/my_extra.txt"),
    "file in cameras/": (lambda out: (out / "cameras" / "my_calib.txt").write_text("c\n"), "cameras/my_calib.txt"),
    "file in a round's output": (lambda out: (out / "round1" / "renders" / "notes.txt").write_text("n\n"),
                                 "round1/renders/notes.txt"),
    "file in view/": (lambda out: (out / "view" / "extra.html").write_text("x\n"), "view/extra.html"),
    "file in report_files/": (lambda out: (out / "report_files" / "mine.png").write_bytes(b"png"),
                              "report_files/mine.png"),
    "edited report.md": (lambda out: _append(out / "report.md"), "report.md"),
    "edited camera file": (lambda out: _append(out / "cameras" / "working" / "cameras.txt"),
                           "cameras/working/cameras.txt"),
    "edited scene.splat": (lambda out: _append(out / "scene.splat"), "scene.splat"),
}


@pytest.mark.parametrize("change", sorted(USER_CHANGES))
def test_user_files_stop_the_resumed_command_with_nothing_changed(finished, tmp_path, monkeypatch, capsys, change):
    """`denoise-gs run` resumed on a finished folder holding a user's file: exit 2, the file named with the fix,
    no traceback, every file as it was; once the file is moved out, the run completes."""
    scene, _ = finished
    out = _copy(finished, tmp_path)
    tiny = TinyStages()
    monkeypatch.setattr(eval.pipeline.run, "product_stages", lambda: _stages(tiny))
    make, named = USER_CHANGES[change]
    make(out)
    before = _tree(out)
    argv = ["run", str(scene), "--out", str(out), "--preset", "fast", "--rounds", "1", "--views", "3",
            "--no-fuse-noisy-splat"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert str(out / named) in err and "move these files out" in err and "Traceback" not in err
    assert _tree(out) == before and not tiny.calls
    (out / named).rename(tmp_path / "kept")
    assert main(argv) == 0
    assert (tmp_path / "kept").is_file() and all((out / p).exists() for p in PUBLISHED)


def test_one_refusal_names_every_such_file(finished, tmp_path):
    scene, _ = finished
    out = _copy(finished, tmp_path)
    for make, _ in USER_CHANGES.values():
        make(out)
    with pytest.raises(UnownedOutputError) as info:
        run_pipeline(scene, out, _cfg(rounds=1), stages=_stages(TinyStages()))
    assert [p.split(" (")[0] for p in info.value.paths] == [str(out / named) for _, named in (
        USER_CHANGES[k] for k in ("file in inputs/", "file in a round's output", "edited scene.splat", "file in view/",
                                  "file in cameras/", "edited camera file", "edited report.md",
                                  "file in report_files/"))]
    assert set(info.value.stages) == {"inputs", "render", "export", "report"}


def test_a_published_file_without_a_record_is_not_replaced(finished, tmp_path):
    """A report the run has no record of (e.g. from a version that did not record it) is not its to replace."""
    scene, _ = finished
    out = _copy(finished, tmp_path)
    (out / "stages" / "report.json").unlink()
    with pytest.raises(UnownedOutputError, match="report.json \\(not written by the stage\\)"):
        run_pipeline(scene, out, _cfg(rounds=1), stages=_stages(TinyStages()))


def test_a_rerun_that_recomputes_withdraws_the_published_result_first(finished, tmp_path):
    """A re-run with another seed, interrupted in its splat stage: the scene, cameras and report of seed 0 are
    gone (they would describe other stages than the folder's), not left beside seed 1's denoised photos."""
    scene, _ = finished
    out = _copy(finished, tmp_path)
    tiny = TinyStages()
    tiny.fail_next.add("splat")
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(scene, out, _cfg(rounds=1, seed=1), stages=_stages(tiny))
    assert dict(tiny.calls) == {"denoise": 1, "align": 1, "splat": 1}
    assert not [p for p in PUBLISHED if (out / p).exists()]
    assert not (out / "stages" / "export.json").exists() and not (out / "stages" / "report.json").exists()
    assert json.loads((out / "round1" / "n2v_model.pt").read_text())["seed"] == stage_seed(1, 1, "denoise")
    resumed = run_pipeline(scene, out, _cfg(rounds=1, seed=1), stages=_stages(TinyStages()))
    report = json.loads(resumed.report_json.read_text())
    assert report["settings"]["seed"] == 1 and all((out / p).exists() for p in PUBLISHED)
    assert report["export"]["num_gaussians"] > 0


def test_a_rerun_with_nothing_to_recompute_keeps_the_published_result(finished, tmp_path):
    scene, _ = finished
    out = _copy(finished, tmp_path)
    kept = {p: (out / p).stat().st_ino for p in ("scene.splat", "view/index.html", "cameras/working/cameras.txt")}
    tiny = TinyStages()
    res = run_pipeline(scene, out, _cfg(rounds=1), stages=_stages(tiny))
    assert not tiny.calls and all(s.skipped for r in res.rounds for s in r.stages.values())
    assert {p: (out / p).stat().st_ino for p in kept} == kept  # not even rewritten
    assert json.loads(res.report_json.read_text())["settings"]["seed"] == 0


def test_copy_train_inputs_refuses_a_folder_holding_other_files(tmp_path):
    dataset = tiny_dataset(tmp_path / "ds")
    folder = tmp_path / "out" / "inputs" / "s"
    copy_train_inputs(dataset, folder)
    (folder / "notes.txt").write_text("mine")
    before = _tree(folder)
    with pytest.raises(InputError, match="notes.txt") as info:
        copy_train_inputs(dataset, folder)
    assert "move these files out" in info.value.fix and info.value.path == folder.parent
    assert _tree(folder) == before
    with pytest.raises(InputError, match="notes.txt"):  # also when it would be rebuilt with other views
        copy_train_inputs(dataset, folder, dataset.train[:2])
    assert _tree(folder) == before


def test_copy_train_inputs_rebuilds_a_folder_of_its_own_links(tmp_path):
    dataset = tiny_dataset(tmp_path / "ds")
    folder = tmp_path / "out" / "inputs" / "s"
    copy_train_inputs(dataset, folder, dataset.train[:2])
    assert copy_train_inputs(dataset, folder) == folder
    assert sorted(p.stem for p in folder.iterdir()) == sorted(dataset.train)
    assert all((folder / dataset.images[n].name).read_bytes() == dataset.images[n].read_bytes() for n in dataset.train)
    assert not [p for p in folder.parent.iterdir() if p.name.startswith(".")]


def test_copy_train_inputs_rebuilds_its_links_after_the_dataset_changed(tmp_path):
    # The dataset's images were re-rendered (new bytes, same names): the recorded links are still this
    # function's own and are rebuilt; a user file beside them is not.
    dataset = tiny_dataset(tmp_path / "ds")
    folder = tmp_path / "out" / "inputs" / "s"
    copy_train_inputs(dataset, folder)
    src = dataset.images[dataset.train[0]]
    src.unlink()  # a new render: a new file under the same name
    src.write_bytes(b"new render")
    copy_train_inputs(dataset, folder)
    assert (folder / src.name).read_bytes() == b"new render"
    (folder / "notes.txt").write_text("the user's")
    with pytest.raises(InputError, match="not written by the stage"):
        copy_train_inputs(dataset, folder)
    assert (folder / "notes.txt").read_text() == "the user's"
