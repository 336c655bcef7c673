"""Triangulation against cv2.triangulatePoints and mrcal's mid2 / geometric, with validity flags."""

import cv2
import mrcal
import numpy as np
import pytest

from mvgeo import transforms as tf
from mvgeo.camera import Camera
from mvgeo.common.errors import DegenerateGeometryError
from mvgeo.triangulate import TriangulationCriteria, triangulate_multiview, triangulate_two_view, triangulate_views_px


def _pair(rng, n=500, noise=1e-3):
    X = rng.normal(size=(n, 3)) + [0, 0, 6]
    T = tf.se3_exp(np.r_[rng.normal(scale=0.2, size=3), -1.0, 0.1, 0.2])[:3]
    X2 = X @ T[:, :3].T + T[:, 3]
    r1 = X + rng.normal(scale=noise, size=X.shape)
    r2 = X2 + rng.normal(scale=noise, size=X.shape)
    return X, T, r1, r2


def _rt01(T):
    # mrcal Rt01 = [R01; t01] maps camera-1 coordinates into camera 0 (our camera 1 = mrcal cam0).
    R, t = T[:, :3], T[:, 3]
    return np.ascontiguousarray(np.vstack([R.T, -R.T @ t]))


def test_mid2_and_midpoint_equal_mrcal(rng):
    X, T, r1, r2 = _pair(rng)
    ours = triangulate_two_view(r1, r2, T, method="mid2")
    ref = mrcal.triangulate_leecivera_mid2(r1, r2, Rt01=_rt01(T), v_are_local=True)
    # Same closed form, float64: agreement to rounding (1e-12 at depth ~6).
    np.testing.assert_allclose(ours.points, ref, atol=1e-12)
    ours = triangulate_two_view(r1, r2, T, method="midpoint")
    ref = mrcal.triangulate_geometric(r1, r2, Rt01=_rt01(T), v_are_local=True)
    np.testing.assert_allclose(ours.points, ref, atol=1e-10)
    assert ours.valid.mean() > 0.95


def test_dlt_equals_opencv_on_exact_data_and_is_accurate_with_noise(rng):
    X, T, r1, r2 = _pair(rng, noise=0.0)
    ours = triangulate_two_view(r1, r2, T, method="dlt")
    Xh = cv2.triangulatePoints(np.eye(4)[:3], T, (r1[:, :2] / r1[:, 2:]).T, (r2[:, :2] / r2[:, 2:]).T)
    np.testing.assert_allclose(ours.points, (Xh[:3] / Xh[3]).T, atol=1e-9)
    np.testing.assert_allclose(ours.points, X, atol=1e-9)
    # With noise our DLT (unit rays, 3 rows per view) and OpenCV's (z = 1, 2 rows) weight the algebraic
    # error differently; both must be about as accurate as each other.
    X, T, r1, r2 = _pair(rng, noise=2e-3)
    ours = triangulate_two_view(r1, r2, T, method="dlt").points
    Xh = cv2.triangulatePoints(np.eye(4)[:3], T, (r1[:, :2] / r1[:, 2:]).T, (r2[:, :2] / r2[:, 2:]).T)
    e_ours = np.median(np.linalg.norm(ours - X, axis=1))
    e_cv = np.median(np.linalg.norm((Xh[:3] / Xh[3]).T - X, axis=1))
    assert e_ours < 1.1 * e_cv


def test_validity_flags_where_mrcal_returns_zero_or_nonsense(rng):
    T = np.c_[np.eye(3), [-1.0, 0, 0]]  # camera 2 centre at x = +1
    # 0: good point; 1: divergent rays (meet behind); 2: parallel rays (point at infinity);
    # 3: nearly parallel (far away, angle 1e-6 rad); 4: point behind both cameras.
    X_good = np.array([0.3, 0.1, 5.0])
    r1 = np.array([X_good, [-0.1, 0, 1], [0, 0, 1], [0, 0, 1], [0.2, 0, -1]])
    r2 = np.array([X_good + T[:, 3], [0.3, 0, 1], [0, 0, 1], [-1e-6, 0, 1], [-0.8, 0, -1]])
    tri = triangulate_two_view(r1, r2, T, method="mid2")
    assert tri.valid.tolist() == [True, False, False, False, False]
    assert np.all(np.isfinite(tri.points))
    assert not tri.in_front[1] and not tri.finite[2] and tri.angle_deg[3] < 0.01 and not tri.in_front[4]
    mr = mrcal.triangulate_leecivera_mid2(r1, r2, Rt01=_rt01(T), v_are_local=True)
    # mrcal reports divergent rays as (0, 0, 0) and returns a huge, unflagged point for case 3.
    assert np.all(mr[1] == 0) and np.linalg.norm(mr[3]) > 1e5
    for method in ("midpoint", "dlt"):
        tri = triangulate_two_view(r1, r2, T, method=method)
        assert tri.valid.tolist() == [True, False, False, False, False], method
        assert np.all(np.isfinite(tri.points))
    with pytest.raises(DegenerateGeometryError):
        triangulate_two_view(r1, r2, np.eye(4)[:3])


def test_multiview_refinement_and_pixels(rng):
    n, V = 200, 5
    X = rng.uniform(-1, 1, (n, 3)) + [0, 0, 5]
    poses = []
    for v in range(V):
        ang = np.radians(-20 + 10 * v)
        R = tf.so3_exp([0, -ang, 0])
        C = np.array([5 * np.sin(ang), 0, 5 - 5 * np.cos(ang)])
        poses.append(np.c_[R, -R @ C])
    poses = np.stack(poses)
    cams = [Camera("OPENCV", 640, 480, np.array([500, 500, 320, 240, -0.05, 0.01, 0.0, 0.0]))] * V
    uv = np.stack([cams[v].project(X @ poses[v, :, :3].T + poses[v, :, 3]).uv_px for v in range(V)])
    uv_noisy = uv + rng.normal(scale=0.5, size=uv.shape)
    observed = rng.random((V, n)) > 0.2
    tri = triangulate_views_px(uv_noisy, cams, poses, observed=observed)
    enough = observed.sum(0) >= 2
    assert np.all(tri.valid[enough] | (tri.angle_deg[enough] < 1.5))
    assert not tri.valid[~enough].any()
    err = np.linalg.norm(tri.points - X, axis=1)[tri.valid]
    # 0.5 px noise at f = 500 and depth 5 with 10-40 deg angles: ~5 mm.
    assert np.median(err) < 0.01
    # Refined (angular Gauss-Newton) is no worse than plain DLT on reprojection error.
    tri_plain = triangulate_views_px(uv_noisy, cams, poses, observed=observed)
    assert tri.reprojection_error_px[tri.valid].max() < 4.0
    rays = np.stack([cams[v].unproject(uv_noisy[v]).rays_cam for v in range(V)])
    dlt = triangulate_multiview(rays, poses, observed=observed, refine=False)
    ref = triangulate_multiview(rays, poses, observed=observed, refine=True)
    both = dlt.valid & ref.valid
    assert np.median(ref.angular_error_deg[both]) <= np.median(dlt.angular_error_deg[both]) + 1e-12
    assert tri_plain.points.shape == (n, 3)
    # Exact data: the multi-view result is exact.
    exact = triangulate_views_px(uv, cams, poses, criteria=TriangulationCriteria(min_angle_deg=0.0))
    np.testing.assert_allclose(exact.points, X, atol=1e-8)


@pytest.mark.parametrize("method", ["mid2", "midpoint", "dlt"])
def test_two_view_fast_path_equals_generic_reference(rng, method):
    """`triangulate_two_view` (two-camera specialised validity) vs the V-generic `_finalise` path."""
    from mvgeo.triangulate import _triangulate_two_view_reference

    X, T, r1, r2 = _pair(rng, n=400, noise=3e-3)
    # Edge cases appended: divergent, parallel, nearly parallel (far), behind both, unobserved (zero ray).
    T = np.c_[T[:, :3], T[:, 3] / np.linalg.norm(T[:, 3])]
    R = T[:, :3]
    extra1 = np.array([[-0.1, 0, 1], [0, 0, 1], [0, 0, 1], [0.2, 0, -1], [0, 0, 0], [0.1, 0.2, 1]])
    d = np.array([[0.3, 0, 1], [0, 0, 1], [-1e-9, 0, 1], [-0.8, 0, -1], [0.1, 0, 1], [0, 0, 0]])
    extra2 = d @ R.T  # directions given in camera 1's frame, expressed in camera 2
    r1 = np.r_[r1, extra1]
    r2 = np.r_[r2, extra2]
    for crit in (TriangulationCriteria(), TriangulationCriteria(min_angle_deg=0.5, max_angular_error_deg=2.0,
                                                                max_range=50.0)):
        fast = triangulate_two_view(r1, r2, T, method=method, criteria=crit)
        ref = _triangulate_two_view_reference(r1, r2, T, method=method, criteria=crit)
        for k in ("valid", "in_front", "finite"):
            np.testing.assert_array_equal(getattr(fast, k), getattr(ref, k), err_msg=k)
        # Same products in the same order except camera 2's depth (a dot product instead of an einsum,
        # it only enters a sign test): agreement to the last bits.
        for k in ("points", "angle_deg", "range", "angular_error_deg"):
            np.testing.assert_allclose(getattr(fast, k), getattr(ref, k), rtol=1e-13, atol=1e-13, err_msg=k)
    assert not fast.finite[-5] and not fast.in_front[-3]


def test_sparse_angular_refinement_equals_dense_reference(rng):
    """`_refine_angular` (observations only, bincount accumulation) vs the dense (V, N) einsum reference."""
    from mvgeo.triangulate import _dlt, _refine_angular, _refine_angular_reference, _unit

    n, V = 300, 8
    X = rng.uniform(-1, 1, (n, 3)) + [0, 0, 5]
    R = np.stack([tf.so3_exp([0.05 * v, -0.1 * v, 0.02]) for v in range(V)])
    C = np.stack([[0.4 * v, 0.1 * np.sin(v), 0.0] for v in range(V)])
    t = -np.einsum("vij,vj->vi", R, C)
    rays = np.einsum("vij,nj->vni", R, X) + t[:, None]
    rays += rng.normal(scale=2e-3, size=rays.shape)  # the angular residual is not zero
    obs = rng.random((V, n)) < 0.35  # sparse tracks, as in the bundle adjustment
    obs[:, :5] = False  # unobserved points (not finite) stay untouched
    obs[:2, 5:8] = True  # two-view tracks
    rays = np.where(obs[..., None], rays, 0.0)
    P = np.concatenate([R, t[..., None]], axis=-1)
    pts, finite = _dlt(rays, P, obs)
    finite &= obs.sum(0) >= 2
    fast = _refine_angular(pts, finite, _unit(rays), R, t, obs)
    ref = _refine_angular_reference(pts, finite, _unit(rays), R, t, obs)
    # Same Gauss-Newton steps; only the order of the per-view sums differs (rounding, 1e-16 relative per
    # step), so the converged points agree to ~1e-12 of their distance.
    np.testing.assert_allclose(fast[finite], ref[finite], rtol=1e-11, atol=1e-11)
    np.testing.assert_array_equal(fast[~finite], pts[~finite])
    assert np.median(np.linalg.norm(fast[finite] - X[finite], axis=1)) < 0.05


def test_dlt_on_observed_rows_equals_the_full_system(rng):
    """`_dlt` (each point's SVD over its observed views only, grouped by their number) against
    `_dlt_reference` (all V views' rows, zeros where unobserved): the same null vectors and the same
    uniqueness verdicts, for tracks of every length from 0 to V views."""
    from mvgeo.triangulate import _dlt, _dlt_reference

    n, V = 400, 7
    X = rng.uniform(-1, 1, (n, 3)) + [0, 0, 5]
    R = np.stack([tf.so3_exp([0.04 * v, -0.08 * v, 0.01]) for v in range(V)])
    C = np.stack([[0.3 * v, 0.1 * np.cos(v), 0.0] for v in range(V)])
    t = -np.einsum("vij,vj->vi", R, C)
    rays = np.einsum("vij,nj->vni", R, X) + t[:, None] + rng.normal(scale=1e-3, size=(V, n, 3))
    obs = rng.random((V, n)) < rng.uniform(0.0, 1.0, n)  # track lengths spread over 0..V
    obs[:, :3] = False
    obs[:, 3:6] = False
    obs[2, 3:6] = True  # one view: the null space is two-dimensional, not unique
    assert set(obs.sum(0)) == set(range(V + 1))
    P = np.concatenate([R, t[..., None]], axis=-1)
    pts, finite = _dlt(rays, P, obs)
    ref, finite_ref = _dlt_reference(rays, P, obs)
    np.testing.assert_array_equal(finite, finite_ref)
    assert not finite[:6].any()
    # The same singular vectors from systems that differ by zero rows: rounding of the SVD only.
    np.testing.assert_allclose(pts[finite], ref[finite], rtol=1e-9, atol=1e-9)
    assert np.median(np.linalg.norm(pts[finite] - X[finite], axis=1)) < 0.05
