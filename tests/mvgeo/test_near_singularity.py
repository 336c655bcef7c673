"""Behaviour near singularities: finite outputs with a validity flag, or a typed error. Never a silent NaN."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mvgeo import transforms as tf
from mvgeo import transforms_torch as tt
from mvgeo import twoview as tv
from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import DegenerateGeometryError
from mvgeo.epipolar import sampson_distance
from mvgeo.metrics import rotation_error_deg
from mvgeo.pnp import estimate_absolute_pose
from mvgeo.ransac import RansacConfig
from mvgeo.triangulate import triangulate_two_view

from ._scenes import H, W, make_two_view

FAST = settings(max_examples=40, deadline=None)
unit_vectors = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1)


@FAST
@given(axis=unit_vectors, log_eps=st.floats(-15, -1), near_pi=st.booleans(), flip=st.booleans())
def test_rotations_near_zero_and_pi(axis, log_eps, near_pi, flip):
    a = np.asarray(axis) / np.linalg.norm(axis)
    angle = np.pi - 10**log_eps if near_pi else 10**log_eps
    w = a * angle
    R = tf.so3_exp(w)
    back = tf.so3_log(R)
    # The log is exact to ~1e-15 absolute (near pi the atan2 form has no 1/sin blow-up).
    np.testing.assert_allclose(tf.so3_exp(back), R, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(back), angle, rtol=1e-9, atol=1e-15)
    q = tf.quat_from_R(R)
    np.testing.assert_allclose(tf.R_from_quat(-q if flip else q), R, atol=1e-14)
    # Torch twin: finite values and gradients at the same points (float64).
    wt = torch.tensor(w, requires_grad=True)
    xi = torch.cat([wt, torch.ones(3, dtype=torch.float64)])
    out = tt.se3_log(tt.se3_exp(xi))
    (g,) = torch.autograd.grad(out.sum(), wt)
    assert torch.isfinite(out).all() and torch.isfinite(g).all()


@FAST
@given(log_angle=st.floats(-9, -3), seed=st.integers(0, 2**16))
def test_near_parallel_rays_are_finite_and_flagged(log_angle, seed):
    rng = np.random.default_rng(seed)
    angle = 10**log_angle
    d = rng.normal(size=3)
    d[2] = abs(d[2]) + 1
    d /= np.linalg.norm(d)
    perp = np.cross(d, [1.0, 0, 0])
    perp /= np.linalg.norm(perp)
    r2 = np.cos(angle) * d + np.sin(angle) * perp
    T = np.c_[np.eye(3), -0.01 * rng.normal(size=3)]
    for method in ("mid2", "midpoint", "dlt"):
        tri = triangulate_two_view(d[None], r2[None], T, method=method)
        assert np.all(np.isfinite(tri.points)) and np.all(np.isfinite(tri.angle_deg))
        assert not tri.valid[0]  # far below the 1.5 deg minimum angle


def test_points_behind_and_at_the_camera_plane():
    cam = Camera("OPENCV", W, H, np.array([500, 500, 320, 240, 0.1, 0.01, 0, 0]))
    pr = cam.project(np.array([[0, 0, -1.0], [1, 1, 0.0], [1e-300, 0, 1e-300], [0, 0, 1e300]]),
                     with_jacobians=True)
    assert pr.valid.tolist() == [False, False, True, True]
    assert np.all(np.isfinite(pr.uv_px)) and np.all(np.isfinite(pr.d_uv_d_point[:2]))


@FAST
@given(k1=st.floats(-0.9, -0.05), frac=st.floats(1.001, 3.0))
def test_unproject_beyond_distortion_limit_reports_non_convergence(k1, frac):
    cam = Camera("SIMPLE_RADIAL", W, H, np.array([300.0, 320.0, 240.0, k1]))
    r_max = 1 / np.sqrt(-3 * k1)  # the radial map r (1 + k1 r^2) peaks here
    rd_max = r_max * (1 + k1 * r_max**2)
    un = cam.unproject(np.array([[320 + 300 * rd_max * frac, 240.0], [320 + 300 * rd_max * 0.5, 240.0]]))
    assert un.valid.tolist() == [False, True]
    assert np.all(np.isfinite(un.rays_cam)) and np.all(np.isfinite(un.residual_px))


def test_zero_and_tiny_baseline_are_reported(rng):
    for baseline in (0.0, 1e-4):
        sc = make_two_view(rng, baseline=baseline, outlier_ratio=0.2, noise_px=0.3)
        res = tv.estimate_relative_pose(sc.u1, sc.u2, sc.K, sc.K)
        assert not res.success and "baseline" in res.reason
        assert np.all(np.isfinite(res.R)) and np.all(np.isfinite(res.t))
        unc = tv.estimate_relative_pose_uncalibrated(sc.u1, sc.u2, (W, H))
        assert not unc.success
        assert unc.focal_px is None or np.isfinite(unc.focal_px)


def test_planar_scene_calibrated_ok_uncalibrated_flagged(rng):
    sc = make_two_view(rng, planar=True, outlier_ratio=0.2, noise_px=0.3)
    # The 5-point solver is not degenerate for planes (Nister 2004).
    res = tv.estimate_relative_pose(sc.u1, sc.u2, sc.K, sc.K)
    assert (res.success and rotation_error_deg(res.R, sc.R) < 2.0) or "ambiguous" in res.reason
    unc = tv.estimate_relative_pose_uncalibrated(sc.u1, sc.u2, (W, H))
    assert not unc.success and unc.homography_ratio >= 0.9 and "homography" in unc.reason


@pytest.mark.parametrize(("noise_px", "max_wrong", "min_right"), [(0.3, 0, 12), (1.0, 4, 10)])
def test_planar_scene_calibrated_rarely_returns_the_planes_other_pose(noise_px, max_wrong, min_right):
    """A plane has two relative poses that explain the matches (the homography's two decompositions, 6-10 deg
    apart on these scenes); the essential fit ended on the wrong one and reported success on 9 of these 24
    scenes at 0.3 px (9 right) and 13 at 1 px (5 right). Now a success is the right pose (the homography's
    decomposition, unrefined: within 0.8 deg at 0.3 px, 3.1 deg at 1 px) or the pair fails naming the ambiguity,
    except on 4
    scenes at 1 px, where the essential model's extra freedom fits the plane's noise (its Sampson distances
    read 0.7 of the noise) and GRIC prefers it (`twoview.homography_gric_margin`)."""
    right = ambiguous = wrong = 0
    for seed in range(24):
        sc = make_two_view(np.random.default_rng(seed), planar=True, outlier_ratio=0.2, noise_px=noise_px)
        res = tv.estimate_relative_pose(sc.u1, sc.u2, sc.K, sc.K)
        if res.success and rotation_error_deg(res.R, sc.R) < 4.0:
            right += 1
        elif res.success:
            wrong += 1
        elif "ambiguous" in res.reason:
            ambiguous += 1
    assert wrong <= max_wrong and right >= min_right and ambiguous >= 4, (right, wrong, ambiguous)


def test_homography_gric_prefers_the_plane_only_without_relief(rng):
    sc = make_two_view(rng, planar=True, outlier_ratio=0.0, noise_px=0.5)
    res = tv.estimate_relative_pose(sc.u1, sc.u2, sc.K, sc.K)
    Hm = cv2.findHomography(sc.u1, sc.u2, 0)[0]
    assert tv.homography_gric_margin(sc.u1, sc.u2, Hm, sampson_distance(res.F, sc.u1, sc.u2)) > 0
    general = make_two_view(rng, outlier_ratio=0.0, noise_px=0.5)
    res = tv.estimate_relative_pose(general.u1, general.u2, general.K, general.K)
    assert res.success
    Hm = cv2.findHomography(general.u1, general.u2, 0)[0]
    assert tv.homography_gric_margin(general.u1, general.u2, Hm, sampson_distance(res.F, general.u1, general.u2)) < 0


def test_all_outliers(rng):
    u1 = rng.uniform(0, [W, H], (200, 2))
    u2 = rng.uniform(0, [W, H], (200, 2))
    K = np.array([[500, 0, W / 2], [0, 500, H / 2], [0, 0, 1.0]])
    # With no inliers RANSAC runs to max_iterations; 300 keeps the test fast and changes nothing else.
    cfg = tv.TwoViewConfig(ransac=RansacConfig(max_iterations=300))
    res = tv.estimate_relative_pose(u1, u2, K, K, config=cfg)
    assert not res.success and np.all(np.isfinite(res.R))
    unc = tv.estimate_relative_pose_uncalibrated(u1, u2, (W, H), config=cfg)
    assert not unc.success
    X = rng.normal(size=(200, 3)) + [0, 0, 5]
    cam = Camera("PINHOLE", W, H, np.array([500, 500, W / 2, H / 2]))
    assert not estimate_absolute_pose(u1, X, cam).success


def test_umeyama_collinear_and_coincident(rng):
    line = np.outer(rng.normal(size=20), [1.0, 2.0, 3.0])
    R = tf.so3_exp([0.3, 0.2, -0.1])
    fit = tf.umeyama(line, 2 * line @ R.T + 1)
    assert not fit.well_posed and np.all(np.isfinite(fit.R)) and fit.rmse < 1e-9
    np.testing.assert_allclose(fit.scale, 2.0, rtol=1e-12)
    with pytest.raises(DegenerateGeometryError):
        tf.umeyama(np.ones((10, 3)), rng.normal(size=(10, 3)))
    with pytest.raises(DegenerateGeometryError):
        tf.R_from_quat(np.zeros(4))


def test_float32_inputs_are_promoted(rng):
    sc = make_two_view(rng, outlier_ratio=0.2)
    res = tv.estimate_relative_pose(sc.u1.astype(np.float32), sc.u2.astype(np.float32), sc.K.astype(np.float32),
                                    sc.K.astype(np.float32))
    assert res.success and res.R.dtype == np.float64
    q = rng.normal(size=(10, 4)).astype(np.float32)
    assert tf.R_from_quat(q).dtype == np.float64
    assert tf.umeyama(sc.X1.astype(np.float32), sc.X1.astype(np.float32)).R.dtype == np.float64
