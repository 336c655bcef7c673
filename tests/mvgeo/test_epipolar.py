"""Minimal/linear epipolar solvers against OpenCV and exact synthetic geometry."""

import cv2
import numpy as np
import pytest

from mvgeo import epipolar as ep
from mvgeo import transforms as tf
from mvgeo.common.errors import ShapeError

from ._scenes import make_two_view


def _unit_sign(M):
    M = M / np.linalg.norm(M)
    return M * np.sign(M.flat[np.argmax(np.abs(M))])


def _essential_violation(E):
    s = np.linalg.svd(E / np.linalg.norm(E), compute_uv=False)
    return abs(s[0] - s[1]) + s[2]


def _random_pair(rng, n):
    X = rng.normal(size=(n, 3)) + [0, 0, 5]
    R = tf.so3_exp(rng.normal(scale=0.3, size=3))
    t = rng.normal(size=3)
    X2 = X @ R.T + t
    return X[:, :2] / X[:, 2:], X2[:, :2] / X2[:, 2:], R, t


def test_essential_5point_contains_true_solution_and_matches_opencv(rng):
    worst = 0.0
    for _ in range(100):
        x1, x2, R, t = _random_pair(rng, 5)
        Es = ep.essential_5point(x1, x2)
        assert 1 <= len(Es) <= 10
        E_true = _unit_sign(ep.essential_from_pose(R, t))
        worst = max(worst, min(np.linalg.norm(_unit_sign(E) - E_true) for E in Es))
        # Every returned solution satisfies the epipolar and essential constraints.
        for E in Es:
            assert np.abs(np.sum(np.c_[x2, np.ones(5)] * (np.c_[x1, np.ones(5)] @ E.T), axis=1)).max() < 1e-10
            s = np.linalg.svd(E, compute_uv=False)
            assert abs(s[0] - s[1]) < 1e-8 and s[2] < 1e-8
        # OpenCV's 5-point (Nister) returns the same solution set (stacked 3x3 blocks). Where a root is
        # ill-conditioned the two differ by up to ~1e-4; then ours must satisfy the essential
        # constraint (s1 = s2, s3 = 0) at least as well as OpenCV's (seen: ours 1e-16, OpenCV 1e-5).
        E_cv, _ = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.LMEDS)
        if E_cv is not None:
            cv_set = [_unit_sign(E_cv[3 * k: 3 * k + 3]) for k in range(E_cv.shape[0] // 3)]
            ours = [_unit_sign(E) for E in Es]
            for Ec in cv_set:
                d = [np.linalg.norm(Ec - Eo) for Eo in ours]
                k = int(np.argmin(d))
                assert d[k] < 1e-6 or (_essential_violation(ours[k]) <= _essential_violation(Ec) and d[k] < 1e-3)
    # Well-conditioned random problems: the true E is recovered to ~1e-10 (eigen-solver accuracy).
    assert worst < 1e-8


def test_fundamental_7_and_8_point(rng):
    for _ in range(50):
        sc = make_two_view(rng, n=20, noise_px=0.0, outlier_ratio=0.0)
        F_true = _unit_sign(ep.fundamental_from_essential(ep.essential_from_pose(sc.R, sc.t), sc.K, sc.K))
        F7 = ep.fundamental_7point(sc.u1[:7], sc.u2[:7])
        assert min(np.linalg.norm(_unit_sign(F) - F_true) for F in F7) < 1e-7
        F8 = ep.fundamental_8point(sc.u1, sc.u2)
        np.testing.assert_allclose(_unit_sign(F8), F_true, atol=1e-8)
    # Noisy: our normalised 8-point equals OpenCV's FM_8POINT (same algorithm) up to sign/scale.
    sc = make_two_view(rng, n=100, noise_px=1.0, outlier_ratio=0.0)
    F_cv, _ = cv2.findFundamentalMat(sc.u1 - 0.5, sc.u2 - 0.5, cv2.FM_8POINT)
    # OpenCV pixels are ours - 0.5: F_ours = T^T F_cv T with T translating by -0.5.
    T = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    np.testing.assert_allclose(_unit_sign(T.T @ F_cv @ T), _unit_sign(ep.fundamental_8point(sc.u1, sc.u2)),
                               atol=1e-6)
    with pytest.raises(ShapeError):
        ep.fundamental_8point(sc.u1[:7], sc.u2[:7])


def test_sampson_distance_matches_opencv_and_geometry(rng):
    sc = make_two_view(rng, n=50, noise_px=2.0, outlier_ratio=0.2)
    F = ep.fundamental_from_essential(ep.essential_from_pose(sc.R, sc.t), sc.K, sc.K)
    d = ep.sampson_distance(F, sc.u1, sc.u2)
    ref = [cv2.sampsonDistance(np.r_[a, 1.0], np.r_[b, 1.0], F) for a, b in zip(sc.u1, sc.u2, strict=True)]
    # OpenCV returns the squared Sampson error.
    np.testing.assert_allclose(d**2, ref, rtol=1e-10)
    exact = make_two_view(rng, n=50, noise_px=0.0, outlier_ratio=0.0)
    F = ep.fundamental_from_essential(ep.essential_from_pose(exact.R, exact.t), exact.K, exact.K)
    assert ep.sampson_distance(F, exact.u1, exact.u2).max() < 1e-9
    # Moving u2 by delta px along the epipolar line normal changes the distance by ~delta/sqrt(2)
    # to first order when both images share the error (Sampson splits it over the 4 coordinates).
    line = np.c_[exact.u1, np.ones(50)] @ F.T
    nrm = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    d2 = ep.sampson_distance(F, exact.u1, exact.u2 + 0.01 * nrm)
    assert np.all((d2 > 0.001) & (d2 <= 0.01 + 1e-9))


def test_decompose_essential_matches_opencv(rng):
    for _ in range(20):
        x1, x2, R, t = _random_pair(rng, 10)
        E = ep.essential_from_pose(R, t)
        Rs, ts = ep.decompose_essential(E)
        R1, R2, tc = cv2.decomposeEssentialMat(E)
        for Rc in (R1, R2):
            assert min(np.abs(Rc - Ri).max() for Ri in Rs) < 1e-10
        assert min(np.abs(tc.ravel() - ti).max() for ti in ts) < 1e-10
        assert any(np.abs(Ri - R).max() < 1e-10 and np.abs(ti - t / np.linalg.norm(t)).max() < 1e-10
                   for Ri, ti in zip(Rs, ts, strict=True))
        for Ri in Rs:
            np.testing.assert_allclose(np.linalg.det(Ri), 1.0, atol=1e-12)
