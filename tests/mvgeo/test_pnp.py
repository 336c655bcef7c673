"""PnP: analytic Jacobian vs finite differences, LM vs OpenCV's refinement, robust estimation."""

import cv2
import numpy as np

from mvgeo import transforms as tf
from mvgeo.camera import Camera
from mvgeo.metrics import rotation_error_deg
from mvgeo.pnp import _residuals, estimate_absolute_pose, refine_pose_lm

CAM = Camera("OPENCV", 640, 480, np.array([500, 505, 320, 240, -0.1, 0.01, 0.001, -0.001]))


def _scene(rng, n=100):
    T = tf.se3_exp(np.r_[rng.normal(scale=0.3, size=3), rng.normal(size=3)])[:3]
    Xc = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), np.ones(n)] * rng.uniform(2, 8, (n, 1))
    return T, tf.apply(tf.invert(T), Xc), CAM.project(Xc).uv_px


def test_pose_jacobian_against_finite_differences(rng):
    T, Xw, uv = _scene(rng, 20)
    r0, _, J = _residuals(T, Xw, uv, CAM, True)
    h = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        rp, _, _ = _residuals((tf.se3_exp(d) @ np.vstack([T, [0, 0, 0, 1]]))[:3], Xw, uv, CAM, False)
        rm, _, _ = _residuals((tf.se3_exp(-d) @ np.vstack([T, [0, 0, 0, 1]]))[:3], Xw, uv, CAM, False)
        # Central differences with h = 1e-7: error ~ eps*|uv|/h ~ 1e-6 px per unit twist.
        np.testing.assert_allclose(J[:, k], (rp - rm) / (2 * h), rtol=1e-5, atol=1e-4)


def test_lm_reaches_the_least_squares_optimum_like_opencv(rng):
    for _ in range(5):
        T, Xw, uv = _scene(rng, 60)
        noisy = uv + rng.normal(scale=1.0, size=uv.shape)
        start = (tf.se3_exp(rng.normal(scale=0.02, size=6)) @ np.vstack([T, [0, 0, 0, 1]]))[:3]
        lm = refine_pose_lm(start, Xw, noisy, CAM)
        assert lm.converged and lm.rmse_px < lm.initial_rmse_px
        # OpenCV's LM on the same problem (its pixels are ours - 0.5, K shifted to match).
        K_cv, d_cv = CAM.to_opencv()
        rvec, tvec = cv2.Rodrigues(start[:, :3])[0], start[:, 3].copy()
        rvec, tvec = cv2.solvePnPRefineLM(Xw, noisy - 0.5, K_cv, d_cv, rvec, tvec,
                                          (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-12))
        T_cv = np.c_[cv2.Rodrigues(rvec)[0], tvec]
        r_cv, _, _ = _residuals(T_cv, Xw, noisy, CAM, False)
        rmse_cv = np.sqrt(np.mean(np.sum(r_cv.reshape(-1, 2) ** 2, axis=1)))
        # Same optimum: our RMSE is not worse than OpenCV's by more than 1e-6 px.
        assert lm.rmse_px <= rmse_cv + 1e-6
        assert rotation_error_deg(lm.cam_from_world[:, :3], T_cv[:, :3]) < 1e-4


def test_robust_pnp_with_outliers(rng):
    for _ in range(3):
        T, Xw, uv = _scene(rng)
        uv = uv + rng.normal(scale=0.5, size=uv.shape)
        out = rng.random(len(uv)) < 0.4
        uv[out] = rng.uniform(0, [640, 480], (out.sum(), 2))
        res = estimate_absolute_pose(uv, Xw, CAM)
        assert res.success
        assert (res.inlier_mask & out).sum() <= 2 and (res.inlier_mask & ~out).sum() >= 0.9 * (~out).sum()
        assert rotation_error_deg(res.cam_from_world[:, :3], T[:, :3]) < 0.2
        assert np.linalg.norm(tf.camera_centre(res.cam_from_world) - tf.camera_centre(T)) < 0.05
    junk = rng.uniform(0, [640, 480], (50, 2))
    res = estimate_absolute_pose(junk, Xw[:50], CAM)
    assert not res.success and np.all(np.isfinite(res.cam_from_world))
