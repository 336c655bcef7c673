"""`denoise-gs run|eval|cost --out`: the output policy (mvgeo.common.output) for resumable folders.

These commands resume inside their folder: a previous output of the same command is reused, never
replaced; anything else is refused with exit 2 before any work, no traceback, every file
byte-identical and no temporary (or empty output folder) left behind.
"""

from __future__ import annotations

import json
import os
import shutil

import pytest

from eval.cli import main
from eval.pipeline import preset, run_pipeline
from mvgeo.common.errors import InputError
from mvgeo.common.output import MANIFEST_NAME
from tests.common._out_policy import assert_refused, fake_previous_output, readonly_access
from tests.eval._tiny_stages import TinyStages, make_scene


def _dataset(root):
    make_scene(root / "images", n=4)
    shutil.copytree(root / "images", root / "clean")
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "split.json").write_text(json.dumps({"train": ["view_001", "view_002", "view_003"],
                                                 "test": ["view_000"]}))
    return root


def test_eval_bad_scene_file_leaves_no_output_folder(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('base = "llff_like"\n[render]\nsupersample = 99\n')
    assert_refused(main, ["eval", bad, "--out", tmp_path / "o" / "x", "--seeds", "1"], capsys, tmp_path,
                   "render.supersample")
    assert not (tmp_path / "o").exists()


def test_run_out_overlapping_the_images(tmp_path, capsys):
    imgs = make_scene(tmp_path / "data" / "images", n=3)
    assert_refused(main, ["run", imgs, "--out", imgs], capsys, tmp_path, "is the input")
    assert_refused(main, ["run", imgs, "--out", tmp_path / "data"], capsys, tmp_path, "contains the input")
    assert_refused(main, ["run", imgs, "--out", imgs / "run"], capsys, tmp_path, "is inside the input")


def test_run_user_folder_file_other_output_and_read_only_parent(tmp_path, capsys, monkeypatch):
    imgs = make_scene(tmp_path / "imgs", n=3)
    user = tmp_path / "p"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    assert_refused(main, ["run", imgs, "--out", user], capsys, tmp_path, "did not write", "thesis.tex")
    f = tmp_path / "file"
    f.write_text("f")
    assert_refused(main, ["run", imgs, "--out", f], capsys, tmp_path, "not a folder")
    ev = fake_previous_output(tmp_path / "ev", "denoise-gs eval")
    assert_refused(main, ["run", imgs, "--out", ev], capsys, tmp_path, "output of `denoise-gs eval`")
    ro = tmp_path / "ro"
    ro.mkdir()
    readonly_access(monkeypatch, ro)
    assert_refused(main, ["run", imgs, "--out", ro / "run"], capsys, tmp_path, "not writable")


def test_run_out_dot(tmp_path, capsys, monkeypatch):
    imgs = make_scene(tmp_path / "imgs", n=3)
    monkeypatch.chdir(imgs)
    assert_refused(main, ["run", ".", "--out", "."], capsys, tmp_path, "is the input")
    monkeypatch.chdir(tmp_path)
    assert_refused(main, ["run", "imgs", "--out", "."], capsys, tmp_path, "contains the input")


def test_eval_and_cost_out_policy(tmp_path, capsys, monkeypatch):
    ds = _dataset(tmp_path / "ds")
    assert_refused(main, ["eval", ds, "--out", ds], capsys, tmp_path, "is the input")
    assert_refused(main, ["eval", ds, "--out", ds / "eval"], capsys, tmp_path, "is inside the input")
    assert_refused(main, ["cost", ds, "--out", ds / "cost"], capsys, tmp_path, "is inside the input")
    user = tmp_path / "p"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    assert_refused(main, ["eval", ds, "--out", user], capsys, tmp_path, "did not write")
    assert_refused(main, ["cost", ds, "--out", user], capsys, tmp_path, "did not write")
    run = fake_previous_output(tmp_path / "run", "denoise-gs run")
    assert_refused(main, ["eval", ds, "--out", run], capsys, tmp_path, "output of `denoise-gs run`")
    ro = tmp_path / "ro"
    ro.mkdir()
    readonly_access(monkeypatch, ro)
    assert_refused(main, ["eval", ds, "--out", ro / "ev"], capsys, tmp_path, "not writable")


def test_run_resumes_its_own_folder_and_refuses_an_added_file(tmp_path):
    imgs = make_scene(tmp_path / "imgs", n=3)
    out = tmp_path / "out"
    cfg = preset("fast", views=3, rounds=1)
    run_pipeline(imgs, out, cfg, stages=TinyStages().stages())
    assert json.loads((out / MANIFEST_NAME).read_text())["command"] == "denoise-gs run"
    tiny = TinyStages()
    run_pipeline(imgs, out, cfg, stages=tiny.stages())  # resumed: no --overwrite needed, nothing re-run
    assert not tiny.calls
    # Without its manifest the folder is not taken for a run's, however run-like its entries look: a
    # user's folder holding `inputs/` and `cameras/` was once resumed into and its files deleted.
    (out / MANIFEST_NAME).unlink()
    before = sorted(os.listdir(out))
    with pytest.raises(InputError, match="did not write"):
        run_pipeline(imgs, out, cfg, stages=tiny.stages())
    assert not tiny.calls and sorted(os.listdir(out)) == before and MANIFEST_NAME not in before
