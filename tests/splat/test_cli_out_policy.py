"""`splat train|render --out`: the output policy (mvgeo.common.output) at the command line.

Every refusal exits 2 before any work (no model is read, nothing is trained), prints no traceback,
leaves the inputs byte-identical and no temporary behind.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from mvgeo.camera import Camera
from mvgeo.common.output import MANIFEST_NAME, write_manifest
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model
from splat.cli import main
from splat.gaussian_model import GaussianModel
from splat.ply import write_gaussian_ply
from tests.common._out_policy import assert_refused, readonly_access


@pytest.fixture()
def model_and_cameras(tmp_path):
    """A tiny trained-model folder M (point_cloud.ply + the `splat train` manifest) and cameras S."""
    rng = np.random.default_rng(0)
    model_dir = tmp_path / "M"
    model_dir.mkdir()
    xyz = rng.normal(size=(20, 3)) * 0.2 + np.array([0, 0, 3.0])
    rgb = rng.integers(0, 255, size=(20, 3)).astype(np.uint8)
    write_gaussian_ply(model_dir / "point_cloud.ply", GaussianModel.from_points(xyz, rgb, sh_degree=0))
    write_manifest(model_dir, "splat train")
    cams = tmp_path / "S"
    pose = np.hstack([np.eye(3), np.zeros((3, 1))])
    write_sparse_model(cams, SparseModel(cameras={1: Camera.pinhole(20.0, 20.0, 8.0, 6.0, 16, 12)},
                                         images=[PosedImage("v0.png", 1, pose)]), binary=False)
    return model_dir, cams


def test_render_out_is_the_model_folder(tmp_path, model_and_cameras, capsys):
    m, s = model_and_cameras
    for extra in ([], ["--overwrite"]):
        assert_refused(main, ["render", m, "--cameras", s, "--out", m, *extra], capsys, tmp_path, "is the input")
    assert_refused(main, ["render", m, "--cameras", s, "--out", s, "--overwrite"], capsys, tmp_path, "is the input")
    assert_refused(main, ["render", m / "point_cloud.ply", "--cameras", s, "--out", m], capsys, tmp_path,
                   "contains the input")


def test_render_will_not_replace_a_trained_model(tmp_path, model_and_cameras, capsys):
    m, s = model_and_cameras
    other = tmp_path / "copy"
    other.mkdir()
    (other / "point_cloud.ply").write_bytes((m / "point_cloud.ply").read_bytes())
    write_manifest(other, "splat train")
    assert_refused(main, ["render", m, "--cameras", s, "--out", other, "--overwrite"], capsys, tmp_path,
                   "output of `splat train`")


def test_render_existing_file_user_folder_and_read_only_parent(tmp_path, model_and_cameras, capsys, monkeypatch):
    m, s = model_and_cameras
    f = tmp_path / "file.png"
    f.write_bytes(b"png")
    assert_refused(main, ["render", m, "--cameras", s, "--out", f, "--overwrite"], capsys, tmp_path, "not a folder")
    user = tmp_path / "p"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    assert_refused(main, ["render", m, "--cameras", s, "--out", user], capsys, tmp_path, "did not write")
    ro = tmp_path / "ro"
    ro.mkdir()
    readonly_access(monkeypatch, ro)
    assert_refused(main, ["render", m, "--cameras", s, "--out", ro / "renders"], capsys, tmp_path, "not writable")


def test_render_previous_output_needs_overwrite(tmp_path, model_and_cameras, capsys):
    m, s = model_and_cameras
    out = tmp_path / "renders"
    assert main(["render", str(m), "--cameras", str(s), "--out", str(out)]) == 0
    assert sorted(os.listdir(out)) == [MANIFEST_NAME, "v0.png"]
    png = (out / "v0.png").read_bytes()
    (out / "v0.png").write_bytes(b"edited")
    err = assert_refused(main, ["render", m, "--cameras", s, "--out", out], capsys, tmp_path, "previous output")
    assert "--overwrite" in err
    # a render the user changed is not replaced, --overwrite or not
    assert_refused(main, ["render", m, "--cameras", s, "--out", out, "--overwrite"], capsys, tmp_path,
                   "changed since")
    (out / "v0.png").write_bytes(png)  # the same bytes again (a new modification time): the command's file
    assert main(["render", str(m), "--cameras", str(s), "--out", str(out), "--overwrite"]) == 0
    assert (out / "v0.png").read_bytes()[:4] == b"\x89PNG"
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]


def test_train_out_overlapping_inputs_and_read_only_parent(tmp_path, model_and_cameras, capsys, monkeypatch):
    data = tmp_path / "data"
    (data / "images").mkdir(parents=True)
    (data / "images" / "v0.png").write_bytes(b"png")
    assert_refused(main, ["train", data, "--out", data], capsys, tmp_path, "is the input")
    assert_refused(main, ["train", data, "--out", data / "out"], capsys, tmp_path, "is inside the input")
    pts = tmp_path / "pts" / "points.ply"
    pts.parent.mkdir()
    pts.write_bytes(b"ply")
    assert_refused(main, ["train", data, "--init", pts, "--out", pts.parent], capsys, tmp_path, "contains the input")
    ro = tmp_path / "ro"
    ro.mkdir()
    readonly_access(monkeypatch, ro)
    # refused at once, not after the training (the data folder here could not even be loaded)
    assert_refused(main, ["train", data, "--out", ro / "out"], capsys, tmp_path, "not writable")
