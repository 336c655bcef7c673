"""DTU-style folder -> evaluation dataset (a synthetic stand-in: tests must not need ../shared)."""

import json

import numpy as np
import pytest

from eval.datasets import dtu_dataset, spread_split
from eval.pipeline import validate_dataset_folder
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, write_image
from mvgeo.sparse_model import read_sparse_model


def _rot(axis_angle):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis_angle).as_matrix()


def _fake_dtu(folder, n=8, seed=0):
    rng = np.random.default_rng(seed)
    (folder / "images").mkdir(parents=True)
    K = np.array([[2892.3, 0.0, 823.2], [0.0, 2883.2, 619.1], [0.0, 0.0, 1.0]])
    scale = np.diag([200.0, 200.0, 200.0, 1.0])
    scale[:3, 3] = [10.0, -5.0, 600.0]
    mats, truth = {}, []
    for i in range(n):
        R = _rot(rng.normal(0, 0.2, 3))
        C = scale[:3, :3] @ rng.normal(0, 0.1, 3) + scale[:3, 3] - R.T @ np.array([0, 0, 550.0])
        P = K @ np.hstack([R, (-R @ C)[:, None]])
        mats[f"world_mat_{i}"] = np.vstack([P, [0, 0, 0, 1]])
        mats[f"scale_mat_{i}"] = scale
        truth.append(P)
        write_image(folder / "images" / f"{i:06d}.png", rng.random((384, 384, 3)))
    np.savez(folder / "cameras.npz", **mats)
    return scale, truth


def test_dtu_dataset_cameras_reproject_like_the_source(tmp_path):
    scale, truth = _fake_dtu(tmp_path / "dtu")
    out = dtu_dataset(tmp_path / "dtu", tmp_path / "ds", size_px=96, train_views=4, test_views=2, sigma_8bit=25)
    ds = validate_dataset_folder(out)
    assert len(ds.train) == 4 and len(ds.test) == 2 and not set(ds.train) & set(ds.test)
    model = read_sparse_model(out / "sparse" / "0")
    rng = np.random.default_rng(1)
    for name in model.names:
        i = int(name[5:8])
        cam, cfw = model.camera_of(name), model.image(name).cam_from_world
        X = rng.normal(0, 0.3, (5, 3))  # normalised world
        Xw = (scale @ np.hstack([X, np.ones((5, 1))]).T).T  # original world (mm)
        uv = (truth[i] @ Xw.T).T
        uv = uv[:, :2] / uv[:, 2:]
        # README mapping to the 384 crop, +0.5 to our pixel convention, then x 96/384.
        expect = np.stack([(uv[:, 0] - 200) * 0.32 + 0.5, uv[:, 1] * 0.32 + 0.5], 1) * (96 / 384)
        x = (cfw[:, :3] @ X.T).T + cfw[:, 3]
        got = np.stack([cam.params[0] * x[:, 0] / x[:, 2] + cam.params[2],
                        cam.params[1] * x[:, 1] / x[:, 2] + cam.params[3]], 1)
        np.testing.assert_allclose(got, expect, atol=1e-6)  # float64 decomposition: exact to rounding
    noisy = read_image(out / "images" / ds.images[ds.train[0]].name)
    clean = read_image(out / "clean" / ds.clean[ds.train[0]].name)
    assert noisy.shape == (96, 96, 3) and 15 / 255 < np.std(noisy - clean) < 30 / 255  # clipped sigma 25
    assert json.loads((out / "meta.json").read_text())["noise"]["sigma_8bit"] == 25


def test_spread_split_and_errors(tmp_path):
    tr, te = spread_split(49, 12, 4)
    assert len(tr) == 12 and len(te) == 4 and tr[0] == 0 and tr[-1] == 48 and not set(tr) & set(te)
    with pytest.raises(InputError):
        spread_split(5, 4, 2)
    with pytest.raises(InputError, match="DTU"):
        dtu_dataset(tmp_path, tmp_path / "out")
