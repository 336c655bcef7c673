"""`mvgeo align|colmap --out`: the output policy (mvgeo.common.output) at the command line.

Every refusal exits 2 before any work, prints no traceback, leaves the inputs byte-identical and
no temporary behind. The replacement cases run the real writer on a stubbed (instant) alignment.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from mvgeo.camera import Camera
from mvgeo.cli import main
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import write_image
from mvgeo.common.output import MANIFEST_NAME
from mvgeo.sparse_model import PosedImage, SparseModel
from tests.common._out_policy import assert_refused, fake_previous_output, readonly_access, snapshot


@pytest.fixture()
def data(tmp_path):
    """tmp/data/images/{a,b}.png (tiny) and tmp/data/cameras.txt."""
    images = tmp_path / "data" / "images"
    images.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        write_image(images / f"{name}.png", rng.random((24, 32, 3)).astype(np.float32))
    (tmp_path / "data" / "cameras.txt").write_text("1 PINHOLE 32 24 30 30 16 12\n")
    return tmp_path / "data"


@pytest.fixture()
def instant_align(monkeypatch):
    """`align_images` replaced by a stub returning a two-view result (the writer stays real)."""
    from mvgeo.align import api

    calls = []

    def fake(paths, cfg, intrinsics=None, cloud_images=None):
        calls.append(paths)
        return _result([p.name for p in paths])

    monkeypatch.setattr(api, "align_images", fake)
    return calls


def _result(names):
    from mvgeo.align import api
    from mvgeo.align.stats import AlignStats

    cam = Camera.pinhole(30.0, 30.0, 16.0, 12.0, 32, 24)
    pose = np.hstack([np.eye(3), np.zeros((3, 1))])
    model = SparseModel(cameras={1: cam}, images=[PosedImage(n, 1, pose) for n in names])
    stats = AlignStats(
        n_images=len(names), n_registered=len(names), input_size_wh=[32, 24], align_size_wh=[32, 24],
        pointmap_size_wh=[32, 24], n_pairs=1, n_pairs_ok=1, n_pairs_verified=1, failed_pairs=[],
        pairs_rejected_by_loops=[], unregistered=[], iterations=1, init_loss=1.0, final_loss=0.5,
        focal_px={n: 30.0 for n in names}, known_intrinsics=False, shared_focal=True, bundle_adjustment=None,
        dense_stereo=None, focal_determined_by_pairs=True, sensitive_features=False, initial_poses="chain",
        candidates=[], pairs_dropped_as_inconsistent=[], pair_consistency_min=1.0, pairs_inconsistent=[], n_points=3,
        mean_confidence=1.0, timings_s={"total": 0.0}, config={})
    return api.AlignResult(model, np.zeros((3, 3)), np.zeros((3, 3), np.uint8), np.ones(3, np.float32), stats)


def test_library_writer_refuses_by_default(tmp_path):
    from mvgeo.align import write_align_result

    res = _result(["a.png", "b.png"])
    user = tmp_path / "user"
    user.mkdir()
    (user / "keep.txt").write_text("k")
    out = write_align_result(tmp_path / "out", res)
    before = snapshot(tmp_path)
    with pytest.raises(InputError, match="did not write"):
        write_align_result(user, res, overwrite=True)
    with pytest.raises(InputError, match="previous output"):
        write_align_result(out, res)
    assert snapshot(tmp_path) == before
    write_align_result(out, res, overwrite=True)
    assert sorted(os.listdir(tmp_path)) == ["out", "user"]


def test_align_out_is_the_image_folder(tmp_path, data, capsys):
    assert_refused(main, ["align", data / "images", "--out", data / "images"], capsys, tmp_path,
                   "is the input")
    assert_refused(main, ["align", data / "images", "--out", data / "images", "--overwrite"], capsys, tmp_path,
                   "is the input")


def test_align_out_contains_or_is_inside_the_images(tmp_path, data, capsys):
    assert_refused(main, ["align", data / "images", "--out", data], capsys, tmp_path, "contains the input")
    assert_refused(main, ["align", data / "images", "--out", data / "images" / "out"], capsys, tmp_path,
                   "is inside the input")
    # the same through `..` and a symbolic link
    (tmp_path / "alias").symlink_to(data)
    assert_refused(main, ["align", data / "images", "--out", tmp_path / "alias" / "images" / ".."], capsys,
                   tmp_path, "contains the input")


def test_align_out_contains_the_intrinsics_file(tmp_path, data, capsys, instant_align):
    other = tmp_path / "imgs"
    other.mkdir()
    for p in (data / "images").iterdir():
        other.joinpath(p.name).write_bytes(p.read_bytes())
    assert_refused(main, ["align", other, "--out", data, "--intrinsics", data / "cameras.txt"], capsys, tmp_path,
                   "contains the input")
    assert not instant_align


def test_align_existing_file_is_kept(tmp_path, data, capsys):
    f = tmp_path / "notes.txt"
    f.write_text("mine")
    assert_refused(main, ["align", data / "images", "--out", f, "--overwrite"], capsys, tmp_path, "not a folder")


def test_align_user_folder_and_other_commands_output_are_kept(tmp_path, data, capsys):
    user = tmp_path / "p"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    assert_refused(main, ["align", data / "images", "--out", user, "--overwrite"], capsys, tmp_path,
                   "did not write", "thesis.tex")
    col = fake_previous_output(tmp_path / "col", "mvgeo colmap")
    assert_refused(main, ["align", data / "images", "--out", col, "--overwrite"], capsys, tmp_path,
                   "output of `mvgeo colmap`")


def test_align_out_dot(tmp_path, data, capsys, monkeypatch, instant_align):
    monkeypatch.chdir(data / "images")  # `.` is the input folder
    assert_refused(main, ["align", ".", "--out", "."], capsys, tmp_path, "is the input")
    monkeypatch.chdir(data)  # `.` holds the input
    assert_refused(main, ["align", "images", "--out", "."], capsys, tmp_path, "contains the input")
    user = tmp_path / "user"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    monkeypatch.chdir(user)  # `.` holds user files
    assert_refused(main, ["align", data / "images", "--out", "."], capsys, tmp_path, "did not write")
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.chdir(empty)  # an empty current folder is written into (never renamed)
    assert main(["align", str(data / "images"), "--out", "."]) == 0
    assert sorted(os.listdir(empty)) == [MANIFEST_NAME, "align.json", "points.ply", "sparse"]
    assert os.getcwd() == str(empty)
    # a previous output in the current folder cannot be replaced while it is the current folder
    assert_refused(main, ["align", data / "images", "--out", ".", "--overwrite"], capsys, tmp_path,
                   "current folder")


def test_align_read_only_parent_fails_before_the_alignment(tmp_path, data, capsys, monkeypatch, instant_align):
    ro = tmp_path / "ro"
    ro.mkdir()
    readonly_access(monkeypatch, ro)
    assert_refused(main, ["align", data / "images", "--out", ro / "out"], capsys, tmp_path, "not writable")
    assert_refused(main, ["colmap", data / "images", "--out", ro / "out"], capsys, tmp_path, "not writable")
    assert not instant_align  # refused before any work


def test_align_previous_output_needs_overwrite(tmp_path, data, capsys, instant_align):
    out = tmp_path / "out"
    assert main(["align", str(data / "images"), "--out", str(out)]) == 0
    first = json.loads((out / MANIFEST_NAME).read_text())
    assert first["command"] == "mvgeo align"
    err = assert_refused(main, ["align", data / "images", "--out", out], capsys, tmp_path, "previous output")
    assert "--overwrite" in err
    ours = (out / "align.json").read_text()
    (out / "align.json").write_text("edited")  # the user's edit: kept, --overwrite or not
    assert_refused(main, ["align", data / "images", "--out", out, "--overwrite"], capsys, tmp_path, "changed since")
    (out / "align.json").write_text(ours)
    assert main(["align", str(data / "images"), "--out", str(out), "--overwrite"]) == 0
    assert json.loads((out / "align.json").read_text())["n_points"] == 3
    again = json.loads((out / MANIFEST_NAME).read_text())["files"]["align.json"]
    assert again["mtime_ns"] != first["files"]["align.json"]["mtime_ns"]  # a new file: replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "out"]  # no .old-/.tmp- sibling


def test_colmap_out_is_the_image_folder(tmp_path, data, capsys):
    assert_refused(main, ["colmap", data / "images", "--out", data / "images"], capsys, tmp_path, "is the input")
    assert_refused(main, ["colmap", data / "images", "--out", data], capsys, tmp_path, "contains the input")


def test_align_calibration_of_another_size_names_its_file(tmp_path, data, capsys, instant_align):
    """The size check of `--intrinsics` names the calibration file, before any image is matched."""
    (tmp_path / "big.txt").write_text("1 PINHOLE 640 480 600 600 320 240\n")
    assert_refused(main, ["align", data / "images", "--out", tmp_path / "out", "--intrinsics", tmp_path / "big.txt"],
                   capsys, tmp_path, str(tmp_path / "big.txt"), "for 640x480 images, the images are 32x24", "fix:")
    assert not instant_align
