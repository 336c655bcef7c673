"""Robust relative pose (own LO-MSAC) against OpenCV and pycolmap on the same seeded scenes."""

import cv2
import numpy as np

from mvgeo import twoview as tv
from mvgeo.common.deps import pycolmap
from mvgeo.metrics import rotation_error_deg, translation_direction_error_deg
from mvgeo.ransac import RansacConfig, required_iterations

from ._scenes import H, W, make_two_view


def _errors(R, t, sc):
    return float(rotation_error_deg(R, sc.R)), float(translation_direction_error_deg(t, sc.t))


def test_calibrated_pose_accuracy_vs_opencv_and_pycolmap(rng):
    ours_r, ours_t, cv_r, cv_t, pc_r, pc_t = [], [], [], [], [], []
    for k in range(6):
        sc = make_two_view(rng, noise_px=0.5, outlier_ratio=0.4)
        res = tv.estimate_relative_pose(sc.u1, sc.u2, sc.K, sc.K, config=tv.TwoViewConfig(
            ransac=RansacConfig(seed=k)))
        assert res.success, res.reason
        # Inliers found: almost all true inliers, almost no outliers (threshold 1 px, noise 0.5 px).
        assert (res.inlier_mask & sc.inlier).sum() >= 0.85 * sc.inlier.sum()
        assert (res.inlier_mask & ~sc.inlier).sum() <= 3
        r, t = _errors(res.R, res.t, sc)
        ours_r.append(r)
        ours_t.append(t)
        # OpenCV reference on the same data (pixels shifted to OpenCV's convention).
        K_cv = sc.K.copy()
        K_cv[:2, 2] -= 0.5
        E, mask = cv2.findEssentialMat(sc.u1 - 0.5, sc.u2 - 0.5, K_cv, method=cv2.USAC_MAGSAC, prob=0.9999,
                                       threshold=1.0)
        _, R_cv, t_cv, _ = cv2.recoverPose(E, sc.u1 - 0.5, sc.u2 - 0.5, K_cv, mask=mask)
        r, t = _errors(R_cv, t_cv.ravel(), sc)
        cv_r.append(r)
        cv_t.append(t)
        cam = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[sc.K[0, 0], sc.K[1, 1], W / 2, H / 2])
        opts = pycolmap.RANSACOptions()
        opts.max_error = 1.0
        opts.random_seed = k  # deterministic reference (-1, the default, depends on global PRNG state)
        pc = pycolmap.estimate_relative_pose(cam, sc.u1, cam, sc.u2, opts)
        rig = pc["cam2_from_cam1"]
        r, t = _errors(rig.rotation.matrix(), rig.translation, sc)
        pc_r.append(r)
        pc_t.append(t)
    # Same data, same noise: our refined pose must be at least as accurate as the references
    # (median over scenes, 25% slack for sampling noise between estimators).
    assert np.median(ours_r) <= 1.25 * max(np.median(cv_r), np.median(pc_r), 0.05)
    assert np.median(ours_t) <= 1.25 * max(np.median(cv_t), np.median(pc_t), 0.2)
    # Absolute sanity for 0.5 px noise, ~100 inliers, ~10 deg parallax.
    assert max(ours_r) < 1.0 and max(ours_t) < 5.0


def test_seeded_ransac_is_deterministic(rng):
    sc = make_two_view(rng)
    cfg = tv.TwoViewConfig(ransac=RansacConfig(seed=7))
    a = tv.estimate_relative_pose(sc.u1, sc.u2, sc.K, sc.K, config=cfg)
    b = tv.estimate_relative_pose(sc.u1, sc.u2, sc.K, sc.K, config=cfg)
    assert np.array_equal(a.R, b.R) and np.array_equal(a.inlier_mask, b.inlier_mask)
    assert required_iterations(0.5, 5, 0.99) == 146  # log(0.01) / log(1 - 1/32)


def test_opencv_backend_runs_through_same_validity(rng):
    sc = make_two_view(rng)
    res = tv.estimate_relative_pose(sc.u1, sc.u2, sc.K, sc.K, config=tv.TwoViewConfig(backend="opencv"))
    assert res.success
    r, t = _errors(res.R, res.t, sc)
    assert r < 1.0 and t < 5.0


def test_uncalibrated_pose_and_focal(rng):
    errs = []
    for k in range(4):
        f_true = rng.uniform(400, 900)
        sc = make_two_view(rng, f=f_true, noise_px=0.5, outlier_ratio=0.3)
        res = tv.estimate_relative_pose_uncalibrated(sc.u1, sc.u2, (W, H), seed=k)
        assert res.success, res.reason
        assert res.homography_ratio < 0.5
        rel = abs(res.focal_px - f_true) / f_true
        errs.append(rel)
        # The reported uncertainty is honest: the error is within 4 sigma.
        assert rel < 4 * res.focal_rel_std + 1e-3
        r, t = _errors(res.R, res.t, sc)
        assert r < 1.5 and t < 6.0
    # Generic geometry with ~10 deg parallax: focal within a few percent.
    assert np.median(errs) < 0.05


def test_focal_from_exact_fundamental(rng):
    from mvgeo.epipolar import essential_from_pose, fundamental_from_essential

    for _ in range(10):
        f = rng.uniform(300, 1500)
        sc = make_two_view(rng, f=f, noise_px=0.0, outlier_ratio=0.0)
        F = fundamental_from_essential(essential_from_pose(sc.R, sc.t), sc.K, sc.K)
        est = tv.focal_from_fundamental(F, (W, H))
        # Exact F: the singular-value gap vanishes only at f (bounded Brent to 1e-10 in log f).
        assert abs(est.focal_px / f - 1) < 1e-6 and est.cost < 1e-8 and not est.at_bound


def test_pose_from_essential_equals_four_full_triangulations(rng):
    """The +-t shortcut picks the same candidate, mask and angles as triangulating all four."""
    from mvgeo.epipolar import essential_from_pose
    from mvgeo.transforms import so3_exp

    for trial in range(20):
        R = so3_exp(rng.normal(scale=0.3, size=3))
        t = rng.normal(size=3)
        t /= np.linalg.norm(t)
        X = rng.normal(size=(300, 3)) + [0, 0, 4 + 4 * rng.random()]
        X2 = X @ R.T + t
        x1 = X[:, :2] / X[:, 2:]
        x2 = X2[:, :2] / X2[:, 2:] + rng.normal(scale=1e-3 * (trial % 3), size=(300, 2))
        x2[:30] = rng.normal(size=(30, 2))  # outliers, some triangulating behind
        E = essential_from_pose(R, t)
        if trial % 4 == 3:
            E = -E  # same candidates, other SVD signs
        got = tv.pose_from_essential(E, x1, x2)
        ref = tv._pose_from_essential_reference(E, x1, x2)
        for a, b in zip(got, ref, strict=True):
            np.testing.assert_array_equal(a, b)
        assert rotation_error_deg(got[0], R) < 1.0


def _sampson_scene(rng):
    """Inlier matches of a generic pair and a start 1-3 deg / a few percent of focal away from the truth."""
    from mvgeo.transforms import so3_exp

    sc = make_two_view(rng, f=650.0, noise_px=0.5, outlier_ratio=0.0)
    R0 = so3_exp(rng.normal(scale=0.03, size=3)) @ sc.R
    t0 = sc.t + rng.normal(scale=0.05, size=3)
    return sc, R0, t0 / np.linalg.norm(t0)


def test_sampson_jacobian_matches_central_differences(rng):
    """The refinement's exact Jacobian (F's derivative through the SO(3) left Jacobian, the unit-sphere
    projection of t and d K^-1 / d log f) against central differences of the residuals, at random points."""
    from scipy.optimize._numdiff import approx_derivative

    for log_f0 in (None, np.log(600.0)):
        sc, R0, t0 = _sampson_scene(rng)
        prob = tv._SampsonProblem(sc.u1, sc.u2, sc.K, sc.K, R0, t0, log_f0, (W / 2, H / 2))
        for _ in range(3):
            p = rng.normal(scale=0.1, size=prob.n_f + 5)
            J = prob.jacobian(p)
            J_ref = approx_derivative(prob.residuals, p, method="3-point")
            # Central differences are exact to O(h^2) ~ 1e-10 relative here; 1e-6 leaves room for rounding.
            assert np.abs(J - J_ref).max() < 1e-6 * np.abs(J_ref).max()


def test_refine_equals_numerical_jacobian_reference(rng):
    """`_refine` (exact Jacobian) reaches the minimum that the same least squares with scipy's numerical
    Jacobian reaches, for the calibrated and the shared-focal problem."""
    from scipy.optimize import least_squares

    c = (W / 2, H / 2)
    for log_f0 in (None, np.log(560.0)):
        sc, R0, t0 = _sampson_scene(rng)
        R, t, f, rel_std = tv._refine(sc.u1, sc.u2, sc.K, sc.K, R0, t0, 0.5, log_f0=log_f0, principal_px=c)
        prob = tv._SampsonProblem(sc.u1, sc.u2, sc.K, sc.K, R0, t0, log_f0, c)
        ref = least_squares(prob.residuals, np.zeros(prob.n_f + 5), method="lm", x_scale="jac", max_nfev=2000,
                            xtol=1e-12, ftol=1e-12)
        _, R_ref, t_ref, _, lf_ref = prob.unpack(ref.x)
        assert rotation_error_deg(R, R_ref) < 1e-5
        assert translation_direction_error_deg(t, t_ref) < 1e-4
        if log_f0 is None:
            assert f is None and rel_std is None
        else:
            assert abs(f / np.exp(lf_ref) - 1) < 1e-6 and 0 < rel_std < 0.1
            assert abs(f / 650.0 - 1) < 5 * rel_std + 1e-3  # and it is the right minimum


def test_relative_rotation_std_matches_the_spread_of_refined_poses(rng):
    """`relative_rotation_std_deg` (the Gauss-Newton covariance at the pose) against a Monte Carlo reference:
    the spread of the rotations `_refine` reaches from 300 independent draws of 0.5 px noise on the same 40
    matches. 300 draws estimate a standard deviation to about 4 % (1 sigma); 15 % also covers the small
    nonlinearity of the problem at this noise."""
    from mvgeo.transforms import so3_log

    sc = make_two_view(rng, n=40, f=650.0, noise_px=0.0, outlier_ratio=0.0)
    predicted = tv.relative_rotation_std_deg(sc.u1, sc.u2, sc.K, sc.K, sc.R, sc.t, noise_floor_px=0.5)
    errs = []
    for _ in range(300):
        u1 = sc.u1 + rng.normal(scale=0.5, size=sc.u1.shape)
        u2 = sc.u2 + rng.normal(scale=0.5, size=sc.u2.shape)
        R, _, _, _ = tv._refine(u1, u2, sc.K, sc.K, sc.R, sc.t, 0.5)
        errs.append(so3_log(R @ sc.R.T))
    empirical = float(np.degrees(np.sqrt(np.linalg.eigvalsh(np.cov(np.array(errs).T)).max())))
    assert 0.85 * empirical < predicted < 1.15 * empirical, (predicted, empirical)
    # Fewer matches pin the rotation less well; too few for five parameters and a noise estimate: inf.
    few = tv.relative_rotation_std_deg(sc.u1[:12], sc.u2[:12], sc.K, sc.K, sc.R, sc.t, noise_floor_px=0.5)
    assert few > predicted
    assert tv.relative_rotation_std_deg(sc.u1[:5], sc.u2[:5], sc.K, sc.K, sc.R, sc.t) == float("inf")
