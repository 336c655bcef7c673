"""`mvgeo.align.guided` (guided matching against its loop reference) and `mvgeo.align.locate` (PnP of a cut-off
view on the main group's points), on synthetic views with SIFT-like unit descriptors."""

from dataclasses import dataclass

import numpy as np
import pytest

from mvgeo.align.checks import PairCheck
from mvgeo.align.guided import fundamental_from_pose, guided_matches, guided_matches_reference
from mvgeo.align.locate import LOCATE_MIN_INLIERS, locate_cut_off, locate_view, main_group_points
from mvgeo.transforms import so3_exp

W, H, F = 400, 300, 420.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])


@dataclass
class Feats:
    """The two fields of `ImageFeatures` the modules read."""

    uv_px: np.ndarray
    desc: np.ndarray

    def root(self) -> np.ndarray:
        return self.desc


def _unit(x):
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def _pose(yaw_deg: float, centre) -> np.ndarray:
    """cam_from_world looking along +z, turned about y, camera centre `centre`."""
    R = so3_exp(np.array([0.0, np.deg2rad(yaw_deg), 0.0]))
    return np.concatenate([R, (-R @ np.asarray(centre, float))[:, None]], axis=1)


def _scene(rng, n_points=600, n_clutter=300, noise_px=0.3, desc_noise=0.05):
    # desc_noise is per component of a 128-d unit vector (components ~0.09): 0.05 is a noise of norm ~0.57.
    """Four views of a textured slab; every point has a descriptor shared (with noise) by its observations,
    and every view has clutter keypoints of its own."""
    X = np.c_[rng.uniform(-1.5, 1.5, n_points), rng.uniform(-1.0, 1.0, n_points), rng.uniform(4.0, 6.0, n_points)]
    D = _unit(rng.normal(size=(n_points, 128)))
    poses = np.stack([_pose(y, [c, 0.0, 0.0]) for y, c in [(0, 0.0), (-4, 0.5), (-8, 1.0), (4, -0.5)]])
    feats = []
    for T in poses:
        xc = X @ T[:, :3].T + T[:, 3]
        uv = (xc @ K.T)[:, :2] / xc[:, 2:3]
        vis = (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H)
        idx = np.flatnonzero(vis)
        uv_obs = uv[idx] + rng.normal(0, noise_px, (len(idx), 2))
        d_obs = _unit(D[idx] + rng.normal(0, desc_noise, (len(idx), 128)))
        clutter_uv = rng.uniform([0, 0], [W, H], (n_clutter, 2))
        clutter_d = _unit(rng.normal(size=(n_clutter, 128)))
        feats.append((Feats(np.r_[uv_obs, clutter_uv], np.r_[d_obs, clutter_d]), idx))
    return X, poses, [f for f, _ in feats], [i for _, i in feats]


def _rel(poses, a, b):
    R = poses[b][:, :3] @ poses[a][:, :3].T
    return R, poses[b][:, 3] - R @ poses[a][:, 3]


def test_fundamental_from_pose_holds_the_epipolar_constraint(rng):
    X, poses, feats, ids = _scene(rng, n_clutter=0, noise_px=0.0)
    Fm = fundamental_from_pose(*_rel(poses, 0, 1), K, K)
    common, a, b = np.intersect1d(ids[0], ids[1], return_indices=True)
    xi = np.c_[feats[0].uv_px[a], np.ones(len(a))]
    xj = np.c_[feats[1].uv_px[b], np.ones(len(b))]
    lines = xi @ Fm.T
    dist = np.abs(np.sum(lines * xj, axis=1)) / np.linalg.norm(lines[:, :2], axis=1)
    assert len(common) > 100 and dist.max() < 1e-6 and np.linalg.norm(Fm) == pytest.approx(1.0)


@pytest.mark.parametrize("chunk", [7, 512])
def test_guided_matches_equal_the_loop_reference(rng, chunk):
    X, poses, feats, _ = _scene(rng, n_points=120, n_clutter=60, desc_noise=0.08)  # noise norm ~0.9: ratio ties
    Fm = fundamental_from_pose(*_rel(poses, 0, 2), K, K)
    fast = guided_matches(feats[0].uv_px, feats[0].desc, feats[2].uv_px, feats[2].desc, Fm, band_px=4.0, chunk=chunk)
    ref = guided_matches_reference(feats[0].uv_px, feats[0].desc, feats[2].uv_px, feats[2].desc, Fm, band_px=4.0)
    assert len(ref) > 20
    np.testing.assert_array_equal(fast, ref)
    empty = guided_matches(feats[0].uv_px[:0], feats[0].desc[:0], feats[2].uv_px, feats[2].desc, Fm)
    assert empty.shape == (0, 2)


def test_guided_matches_are_correct_under_the_true_geometry_and_few_under_a_turned_one(rng):
    X, poses, feats, ids = _scene(rng, desc_noise=0.06)
    m = guided_matches(feats[0].uv_px, feats[0].desc, feats[1].uv_px, feats[1].desc,
                       fundamental_from_pose(*_rel(poses, 0, 1), K, K), band_px=2.0)
    n0 = len(ids[0])
    true = (m[:, 0] < n0) & (m[:, 1] < len(ids[1]))
    true &= ids[0][np.minimum(m[:, 0], n0 - 1)] == ids[1][np.minimum(m[:, 1], len(ids[1]) - 1)]
    assert len(m) > 300 and true.mean() > 0.98
    R, t = _rel(poses, 0, 1)
    turned = guided_matches(feats[0].uv_px, feats[0].desc, feats[1].uv_px, feats[1].desc,
                            fundamental_from_pose(so3_exp(np.array([0.0, 0.0, np.deg2rad(10)])) @ R, t, K, K),
                            band_px=2.0)
    assert len(turned) < 0.2 * len(m)


def _cam(poses):
    return poses, np.full(len(poses), F)


def test_a_view_placed_right_is_located_and_one_turned_20_deg_is_not(rng):
    X, poses, feats, _ = _scene(rng, desc_noise=0.06)
    cams, focal = _cam(poses)
    pts, desc = main_group_points(cams, focal, (W, H), feats, [(0, 1), (1, 3)])
    assert len(pts) > 400
    # The points are the scene's. Depth noise of a pair: z^2 / (f b) * sqrt(2) * 0.3 px = 0.05 m at z = 5 m on the
    # 0.5 m baseline of (0, 1) (0.025 m on (1, 3)'s 1 m): the median distance to the nearest true point is below.
    d = np.linalg.norm(pts[:, None] - X[None], axis=2).min(axis=1)
    assert np.median(d) < 0.05
    right = locate_view(2, cams, focal, (W, H), feats, pts, desc)
    assert right.ok and right.n_inliers > 200 and right.rotation_deg < 0.2
    wrong = cams.copy()
    wrong[2, :, :3] = so3_exp(np.array([0.0, np.deg2rad(20), 0.0])) @ wrong[2, :, :3]
    turned = locate_view(2, wrong, focal, (W, H), feats, pts, desc)
    assert not turned.ok and turned.rotation_deg == pytest.approx(20.0, abs=0.5)
    # PnP's own pose is the true one, whatever the solution said: `relocate` starts from it.
    assert turned.placed_elsewhere and not right.placed_elsewhere
    np.testing.assert_allclose(turned.cam_from_world, poses[2], atol=0.02)


def test_a_view_that_shares_no_points_is_not_located(rng):
    X, poses, feats, _ = _scene(rng)
    cams, focal = _cam(poses)
    pts, desc = main_group_points(cams, focal, (W, H), feats, [(0, 1)])
    stranger = list(feats)
    stranger[2] = Feats(rng.uniform([0, 0], [W, H], (800, 2)), _unit(rng.normal(size=(800, 128))))
    out = locate_view(2, cams, focal, (W, H), stranger, pts, desc)
    assert out.n_inliers < LOCATE_MIN_INLIERS and not out.ok
    assert not locate_view(2, cams, focal, (W, H), feats, pts[:0], desc[:0]).ok


def test_locate_cut_off_triangulates_the_explained_pairs_near_the_view(rng):
    X, poses, feats, _ = _scene(rng, desc_noise=0.06)
    cams, focal = _cam(poses)
    checks = [PairCheck(0, 1, 200, 0.99), PairCheck(0, 3, 200, 0.99), PairCheck(1, 3, 200, 0.99),
              PairCheck(1, 2, 15, 0.9, 25.0)]
    bad = [checks[-1]]
    (loc,) = locate_cut_off(cams, focal, (W, H), feats, checks, bad, [2])
    assert loc.view == 2 and loc.ok
    # Without an explained pair that includes one of its partners there is nothing to locate it on.
    (none,) = locate_cut_off(cams, focal, (W, H), feats, [PairCheck(0, 3, 200, 0.99), checks[-1]], bad, [2])
    assert none.n_points == 0 and not none.ok
