"""`denoise n2v|select --out`: the output policy (mvgeo.common.output) at the command line.

Every refusal exits 2 before any work (no training), prints no traceback, leaves the inputs
byte-identical and no temporary behind.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from denoise.cli import main
from mvgeo.camera import Camera
from mvgeo.common.imageio import write_image
from mvgeo.common.output import MANIFEST_NAME
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model
from tests.common._out_policy import assert_refused, fake_previous_output, readonly_access


@pytest.fixture()
def noisy(tmp_path):
    folder = tmp_path / "X"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        write_image(folder / f"{name}.png", rng.random((32, 32, 3)).astype(np.float32))
    return folder


@pytest.fixture()
def model(tmp_path, noisy):
    """A COLMAP model S of the two images of X (poses on a line)."""
    sparse = tmp_path / "S"
    images = [PosedImage(f"{n}.png", 1, np.hstack([np.eye(3), np.array([[i], [0.0], [0.0]])]))
              for i, n in enumerate(("a", "b"))]
    write_sparse_model(sparse, SparseModel(cameras={1: Camera.pinhole(30.0, 30.0, 16.0, 16.0, 32, 32)},
                                           images=images), binary=False)
    return sparse


def test_n2v_out_is_the_noisy_folder(tmp_path, noisy, capsys):
    for extra in ([], ["--overwrite"]):
        assert_refused(main, ["n2v", noisy, "--out", noisy, *extra], capsys, tmp_path, "is the input")
    assert_refused(main, ["n2v", noisy, "--out", noisy / "den"], capsys, tmp_path, "is inside the input")
    assert_refused(main, ["n2v", noisy, "--out", tmp_path], capsys, tmp_path, "contains the input")


def test_n2v_existing_file_user_folder_other_output_read_only(tmp_path, noisy, capsys, monkeypatch):
    f = tmp_path / "f.txt"
    f.write_text("mine")
    assert_refused(main, ["n2v", noisy, "--out", f, "--overwrite"], capsys, tmp_path, "not a folder")
    user = tmp_path / "p"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    assert_refused(main, ["n2v", noisy, "--out", user, "--overwrite"], capsys, tmp_path, "did not write")
    other = fake_previous_output(tmp_path / "renders", "splat render")
    assert_refused(main, ["n2v", noisy, "--out", other, "--overwrite"], capsys, tmp_path, "output of `splat render`")
    ro = tmp_path / "ro"
    ro.mkdir()
    readonly_access(monkeypatch, ro)
    assert_refused(main, ["n2v", noisy, "--out", ro / "out"], capsys, tmp_path, "not writable")


def test_n2v_out_dot(tmp_path, noisy, capsys, monkeypatch):
    monkeypatch.chdir(noisy)
    assert_refused(main, ["n2v", ".", "--out", "."], capsys, tmp_path, "is the input")
    monkeypatch.chdir(tmp_path)
    assert_refused(main, ["n2v", "X", "--out", "."], capsys, tmp_path, "contains the input")


def test_n2v_previous_output_needs_overwrite(tmp_path, noisy, capsys):
    out = tmp_path / "out"
    fast = ["--steps", "1", "--passes", "0", "--preset", "fast"]
    assert main(["n2v", str(noisy), "--out", str(out), *fast]) == 0
    assert json.loads((out / MANIFEST_NAME).read_text())["command"] == "denoise n2v"
    err = assert_refused(main, ["n2v", noisy, "--out", out, *fast], capsys, tmp_path, "previous output")
    assert "--overwrite" in err
    (out / "notes.txt").write_text("the user's")  # not the command's: the output is kept
    assert_refused(main, ["n2v", noisy, "--out", out, *fast, "--overwrite"], capsys, tmp_path, "notes.txt")
    (out / "notes.txt").unlink()
    first = (out / "report.json").stat().st_mtime_ns
    assert main(["n2v", str(noisy), "--out", str(out), *fast, "--overwrite"]) == 0
    assert json.loads((out / "report.json").read_text())["steps"] == 1
    assert (out / "report.json").stat().st_mtime_ns != first  # replaced
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]


def test_select_out_existing_folder(tmp_path, noisy, model, capsys):
    existing = tmp_path / "EXISTING_DIR"
    existing.mkdir()
    for extra in ([], ["--overwrite"]):
        assert_refused(main, ["select", model, "--images", noisy, "--k", "1", "--out", existing, *extra], capsys,
                       tmp_path, "is a folder")


def test_select_out_file_policy(tmp_path, noisy, model, capsys, monkeypatch):
    assert_refused(main, ["select", model, "--images", noisy, "--out", noisy / "sel.json"], capsys, tmp_path,
                   "is inside the input")
    sel = tmp_path / "sel.json"
    sel.write_text("mine")
    err = assert_refused(main, ["select", model, "--images", noisy, "--k", "1", "--out", sel], capsys, tmp_path,
                         "already exists")
    assert "--overwrite" in err
    # The user's own file is never replaced, --overwrite or not; a selection this command wrote is.
    assert_refused(main, ["select", model, "--images", noisy, "--k", "1", "--out", sel, "--overwrite"], capsys,
                   tmp_path, "no record of being written by `denoise select`")
    assert sel.read_text() == "mine"
    ours = tmp_path / "ours.json"
    assert main(["select", str(model), "--images", str(noisy), "--k", "1", "--out", str(ours)]) == 0
    assert main(["select", str(model), "--images", str(noisy), "--k", "1", "--out", str(ours), "--overwrite"]) == 0
    assert len(json.loads(ours.read_text())["selected"]) == 1
    # --out a symbolic link to a selection this command wrote: written through the link, which stays
    link = tmp_path / "link.json"
    link.symlink_to(ours)
    assert main(["select", str(model), "--images", str(noisy), "--k", "1", "--out", str(link), "--overwrite"]) == 0
    assert link.is_symlink() and len(json.loads(ours.read_text())["selected"]) == 1
    ro = tmp_path / "ro"
    ro.mkdir()
    readonly_access(monkeypatch, ro)
    assert_refused(main, ["select", model, "--images", noisy, "--out", ro / "sel.json"], capsys, tmp_path,
                   "not writable")
