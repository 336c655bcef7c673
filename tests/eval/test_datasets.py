"""DTU-style folder -> evaluation dataset via `eval.datasets` (a synthetic stand-in: tests must not need ../shared)."""

import json

import numpy as np
import pytest

from eval.datasets import cluster_split, dtu_dataset, spread_split
from eval.pipeline import validate_dataset_folder
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, write_image
from mvgeo.sparse_model import read_sparse_model


def _rot(axis_angle):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis_angle).as_matrix()


def _fake_dtu(folder, n=8, seed=0, grid=False):
    rng = np.random.default_rng(seed)
    (folder / "images").mkdir(parents=True)
    K = np.array([[2892.3, 0.0, 823.2], [0.0, 2883.2, 619.1], [0.0, 0.0, 1.0]])
    scale = np.diag([200.0, 200.0, 200.0, 1.0])
    scale[:3, 3] = [10.0, -5.0, 600.0]
    mats, truth = {}, []
    for i in range(n):
        # grid: 3x3 viewing directions 0.15 rad apart (the cluster layout needs an interior view)
        R = _rot([0.15 * (i // 3 - 1), 0.15 * (i % 3 - 1), 0.0]) if grid else _rot(rng.normal(0, 0.2, 3))
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
        i = int(name[:6])  # the source image's stem, 000000..
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
    assert json.loads((out / "meta.json").read_text())["noise"]["params"]["sigma_8bit"] == 25


def test_dtu_projection_of_negative_scale_is_the_same_camera(tmp_path):
    from eval.real.dtu import read_dtu

    _fake_dtu(tmp_path / "dtu", n=3)
    (tmp_path / "neg").mkdir()
    (tmp_path / "neg" / "images").symlink_to(tmp_path / "dtu" / "images")
    mats = dict(np.load(tmp_path / "dtu" / "cameras.npz"))
    for key in [k for k in mats if k.startswith("world_mat_")]:
        mats[key] = np.vstack([-mats[key][:3], mats[key][3:]])  # -P: the same projection
    np.savez(tmp_path / "neg" / "cameras.npz", **mats)
    for a, b in zip(read_dtu(tmp_path / "dtu").views, read_dtu(tmp_path / "neg").views, strict=True):
        np.testing.assert_allclose(b.camera.params, a.camera.params, rtol=1e-12)
        np.testing.assert_allclose(b.cam_from_world, a.cam_from_world, atol=1e-12)


def test_spread_split_and_errors(tmp_path):
    tr, te = spread_split(49, 12, 4)
    assert len(tr) == 12 and len(te) == 4 and tr[0] == 0 and tr[-1] == 48 and not set(tr) & set(te)
    with pytest.raises(InputError):
        spread_split(5, 4, 2)
    with pytest.raises(InputError, match="DTU"):
        dtu_dataset(tmp_path, tmp_path / "out")


def test_cluster_split_takes_the_most_alike_views_and_holds_out_interior_ones():
    # A 7x7 grid of viewing directions, 10 deg apart, around +z; a cluster of 25 around the centre.
    a = np.radians(10.0) * np.arange(-3, 4)
    ax, ay = np.meshgrid(a, a)
    d = np.stack([np.tan(ax.ravel()), np.tan(ay.ravel()), np.ones(49)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tr, te = cluster_split(d, 21, 4)
    chosen = np.array(tr + te)
    # The 25 views closest to +z: the 21 within two steps (corners excluded) and the 4 three steps out.
    assert len(chosen) == 25 and len(set(chosen.tolist())) == 25 and len(te) == 4
    assert np.all(np.degrees(np.arccos(d[chosen] @ np.array([0.0, 0.0, 1.0]))) < 30.5)
    assert 24 in te  # the centre view is held out first
    # Reference: in the tangent plane at the cluster's centre, every held-out view lies inside the convex
    # hull of the training views next to it (within 15 deg).
    from scipy.spatial import Delaunay

    plane = lambda v: v[..., :2] / v[..., 2:]  # noqa: E731  (gnomonic projection around +z)
    for t in te:
        near = [i for i in tr if np.degrees(np.arccos(np.clip(d[i] @ d[t], -1, 1))) < 15.0]
        assert len(near) >= 3 and Delaunay(plane(d[near])).find_simplex(plane(d[t])) >= 0, (t, near)
    with pytest.raises(InputError, match="room for only"):
        cluster_split(d, 4, 9)
    with pytest.raises(InputError, match="cannot split"):
        cluster_split(d, 40, 10)


def test_dtu_dataset_cluster_layout_and_unknown_layout(tmp_path):
    _fake_dtu(tmp_path / "dtu", n=9, grid=True)
    out = dtu_dataset(tmp_path / "dtu", tmp_path / "ds", size_px=64, train_views=5, test_views=1, layout="cluster")
    split = json.loads((out / "split.json").read_text())
    assert len(split["train"]) == 5 and split["test"] == ["000004.png"]  # the grid's centre
    assert json.loads((out / "meta.json").read_text())["split"]["layout"] == "cluster"
    with pytest.raises(InputError, match="layout"):
        dtu_dataset(tmp_path / "dtu", tmp_path / "ds2", layout="orbit")
    assert not (tmp_path / "ds2").exists()


def test_dtu_original_size_keeps_k_and_other_sizes_are_refused(tmp_path):
    from eval.real import import_dataset

    scale, truth = _fake_dtu(tmp_path / "dtu", n=4)
    for p in (tmp_path / "dtu" / "images").glob("*.png"):  # the original 1600x1200 frames (flat: small files)
        write_image(p, np.full((1200, 1600, 3), 0.5, np.float32))
    out = import_dataset("dtu", tmp_path / "dtu", tmp_path / "ds", test=1, max_size_px=400)
    model = read_sparse_model(out / "sparse" / "0")
    X = np.random.default_rng(2).normal(0, 0.3, (5, 3))
    for name in model.names:
        cam, cfw = model.camera_of(name), model.image(name).cam_from_world
        uv = (truth[int(name[:6])] @ (scale @ np.hstack([X, np.ones((5, 1))]).T)).T
        expect = (uv[:, :2] / uv[:, 2:] + 0.5) * 0.25  # OpenCV centres -> ours, then 1600 -> 400
        x = (cfw[:, :3] @ X.T).T + cfw[:, 3]
        got = np.stack([cam.fx * x[:, 0] / x[:, 2] + cam.cx, cam.fy * x[:, 1] / x[:, 2] + cam.cy], 1)
        np.testing.assert_allclose(got, expect, atol=1e-6)
        assert cam.size_wh == (400, 300)
    write_image(tmp_path / "dtu" / "images" / "000000.png", np.zeros((100, 100, 3)))
    with pytest.raises(InputError, match="different sizes"):
        import_dataset("dtu", tmp_path / "dtu", tmp_path / "ds2")
    for p in (tmp_path / "dtu" / "images").glob("*.png"):
        write_image(p, np.zeros((100, 100, 3)))
    with pytest.raises(InputError, match="original 1600x1200"):
        import_dataset("dtu", tmp_path / "dtu", tmp_path / "ds2")
