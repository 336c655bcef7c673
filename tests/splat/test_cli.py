"""`splat train` / `splat render`: outputs (optimised COLMAP cameras, curve PNG) and input errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mvgeo.camera import Camera
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import read_sparse_model, write_sparse_model
from splat.cli import main
from tests.common.cli_contract import assert_refused
from tests.splat.test_train import _write_dataset, scene  # noqa: F401  (module fixture)


def _rot_angle(R):
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("optimize", [True, False])
def test_train_writes_the_optimised_cameras(tmp_path, scene, optimize):  # noqa: F811
    names = _write_dataset(tmp_path / "data", scene)
    out = tmp_path / "out"
    flag = "--optimize-poses" if optimize else "--no-optimize-poses"
    assert main(["train", str(tmp_path / "data"), "--out", str(out), "--iters", "25", flag]) == 0
    written = read_sparse_model(out / "sparse" / "0")
    given = read_sparse_model(tmp_path / "data" / "sparse" / "0")
    assert written.names == names[:4]
    for name in written.names:
        np.testing.assert_array_equal(written.camera_of(name).params, given.camera_of(name).params)
    moved = []
    for name in written.names:
        a, b = written.image(name).cam_from_world, given.image(name).cam_from_world
        d_rot, d_t = _rot_angle(a[:, :3] @ b[:, :3].T), float(np.linalg.norm(a[:, 3] - b[:, 3]))
        # Learned corrections are small (lr 1e-4, 25 steps).
        assert d_rot < 0.05 and d_t < 0.05, (name, d_rot, d_t)
        moved.append(float(np.abs(a - b).max()))
    # Unchanged poses survive the text round trip (quaternion + translation) to ~1e-15.
    assert moved[0] < 1e-9  # view 0 fixes the gauge
    if optimize:
        assert min(moved[1:]) > 1e-7, moved  # the others were optimised and written
    else:
        assert max(moved) < 1e-9, moved
    curve = read_image(out / "train_curve.png")
    assert curve.ndim == 3 and curve.shape[0] > 100 and curve.shape[1] > 300 and curve.std() > 0.01
    history = json.loads((out / "history.json").read_text())
    assert history["iteration"][-1] == 24 and len(history["loss"]) == len(history["iteration"])
    report = json.loads((out / "report.json").read_text())
    assert report["train_views"] == names[:4] and report["config"]["optimize_poses"] is optimize


def _expect_error(capsys, argv, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err
    for needle in needles:
        assert needle in err, err


def test_train_input_errors_name_the_problem(tmp_path, scene, capsys):  # noqa: F811
    out = tmp_path / "out"
    data = tmp_path / "missing_image"
    _write_dataset(data, scene)
    (data / "images" / "v2.png").unlink()
    _expect_error(capsys, ["train", str(data), "--out", str(out)], "v2.png", "not in images/")

    data = tmp_path / "split_unknown"
    _write_dataset(data, scene)
    (data / "split.json").write_text(json.dumps({"train": ["v0.png", "nope.png"], "test": []}))
    _expect_error(capsys, ["train", str(data), "--out", str(out)], "nope.png", "split.json")

    data = tmp_path / "split_corrupt"
    _write_dataset(data, scene)
    (data / "split.json").write_text("{not json")
    _expect_error(capsys, ["train", str(data), "--out", str(out)], "split.json")

    data = tmp_path / "distorted"
    _write_dataset(data, scene)
    model = read_sparse_model(data / "sparse" / "0")
    cam = scene["camera"]
    model.cameras = {1: Camera("OPENCV", cam.width, cam.height, [cam.fx, cam.fy, cam.cx, cam.cy, 0.1, 0, 0, 0])}
    write_sparse_model(data / "sparse" / "0", model, binary=False)
    _expect_error(capsys, ["train", str(data), "--out", str(out), "--iters", "2"], "distortion", "undistort")

    data = tmp_path / "no_sparse"
    _write_dataset(data, scene)
    for f in (data / "sparse" / "0").iterdir():
        f.unlink()
    _expect_error(capsys, ["train", str(data), "--out", str(out)], "sparse/0")

    with pytest.raises(SystemExit) as exc:  # checked by the parser
        main(["train", str(tmp_path / "missing_image"), "--out", str(out), "--iters", "0"])
    assert exc.value.code == 2 and "argument --iters" in capsys.readouterr().err
    _expect_error(capsys, ["train", str(tmp_path / "missing_image"), "--out", str(out), "--init",
                           str(tmp_path / "none.ply")])
    assert not out.exists()  # no half-written outputs


@pytest.mark.parametrize(("content", "message"), [
    (b'{"train": 5}', "'train' must be a list of image names"),
    (b'{"train": "v0.png", "test": []}', "'train' must be a list of image names"),
    (b'{"train": [0, 1], "test": []}', "'train' must be a list of image names"),
    (b'{"test": ["v4.png"]}', "no 'train' list"),
    (b'["v0.png"]', "not an object"),
    (b'{"train": ["caf\xe9.png"], "test": []}', "not UTF-8 text"),
    (b'{"train": [', "not valid JSON"),
])
def test_train_refuses_a_malformed_split_json(tmp_path, scene, capsys, content, message):  # noqa: F811
    data = tmp_path / "data"
    _write_dataset(data, scene)
    (data / "split.json").write_bytes(content)
    assert_refused(main, ["train", data, "--out", tmp_path / "out", "--iters", "2"], capsys, inputs=[data],
                   watch=[tmp_path], message=[str(data / "split.json"), message, "fix:"])


@pytest.mark.parametrize(("content", "message"), [(b"not a numpy file", "not a NumPy .npy file, or a damaged one"),
                                                  (None, "depth map has shape (3, 4)")])
def test_train_init_depth_refuses_a_bad_depth_map(tmp_path, scene, capsys, content, message):  # noqa: F811
    data = tmp_path / "data"
    names = _write_dataset(data, scene)
    cam = scene["camera"]
    (data / "depth").mkdir()
    for name in names:
        np.save(data / "depth" / f"{Path(name).stem}.npy", np.ones((cam.height, cam.width), np.float32))
    bad = data / "depth" / "v1.npy"
    if content is None:
        np.save(bad, np.ones((3, 4), np.float32))
    else:
        bad.write_bytes(content)
    assert_refused(main, ["train", data, "--out", tmp_path / "out", "--iters", "2", "--init", "depth"], capsys,
                   inputs=[data], watch=[tmp_path], message=[str(bad), message, "fix:"])


def test_render_input_errors(tmp_path, scene, capsys):  # noqa: F811
    data = tmp_path / "data"
    _write_dataset(data, scene)
    out = tmp_path / "model"
    assert main(["train", str(data), "--out", str(out), "--iters", "3"]) == 0
    _expect_error(capsys, ["render", str(out), "--cameras", str(tmp_path / "nowhere"), "--out", str(tmp_path / "r")])
    _expect_error(capsys, ["render", str(tmp_path / "nomodel"), "--cameras", str(data / "sparse" / "0"),
                           "--out", str(tmp_path / "r")])
    assert not (tmp_path / "r").exists()
