"""Camera models against cv2.projectPoints / undistortPoints, mrcal.project / unproject and pycolmap."""

import cv2
import mrcal
import numpy as np
import pytest

from mvgeo.camera import Camera
from mvgeo.common.errors import InputError

W, H = 640, 480


def make_camera(model, rng):
    f = rng.uniform(400, 700)
    fy = f * rng.uniform(0.95, 1.05)
    cx, cy = W / 2 + rng.uniform(-10, 10), H / 2 + rng.uniform(-10, 10)
    k = rng.uniform(-1, 1, 8) * np.array([0.1, 0.02, 0.002, 0.002, 0.005, 0.05, 0.01, 0.002])
    params = {
        "SIMPLE_PINHOLE": [f, cx, cy],
        "PINHOLE": [f, fy, cx, cy],
        "SIMPLE_RADIAL": [f, cx, cy, k[0]],
        "OPENCV": [f, fy, cx, cy, *k[:4]],
        "FULL_OPENCV": [f, fy, cx, cy, *k],
    }[model]
    return Camera(model, W, H, np.array(params))


def points_in_view(rng, n, half_fov=0.6):
    xy = rng.uniform(-half_fov, half_fov, (n, 2))
    z = rng.uniform(0.5, 20, (n, 1))
    return np.c_[xy, np.ones(n)] * z


MODELS = ["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "OPENCV", "FULL_OPENCV"]


@pytest.mark.parametrize("model", MODELS)
def test_project_matches_opencv_mrcal_pycolmap(model, rng):
    for _ in range(10):
        cam = make_camera(model, rng)
        P = points_in_view(rng, 200)
        pr = cam.project(P, with_jacobians=True)
        assert pr.valid.all()
        # OpenCV: top-left pixel centre at (0, 0) -> add 0.5.
        K_cv, d_cv = cam.to_opencv()
        uv_cv, J_cv = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K_cv, d_cv if d_cv.size else None)
        # 1e-9 px: both evaluate the same polynomial in float64 (differences are rounding, ~1e-13).
        np.testing.assert_allclose(pr.uv_px, uv_cv[:, 0] + 0.5, atol=1e-9)
        # OpenCV's Jacobian w.r.t. tvec equals d uv / d point when R = I, t = 0.
        J_t = J_cv[:, 3:6].reshape(-1, 2, 3)
        np.testing.assert_allclose(pr.d_uv_d_point, J_t, rtol=1e-7, atol=1e-7)
        # mrcal: same 0.5 shift; gradients compared directly (SIMPLE models: d/df = d/dfx + d/dfy).
        lens, intr = cam.to_mrcal()
        q, dq_dp, dq_di = mrcal.project(np.ascontiguousarray(P), lens, intr, get_gradients=True)
        np.testing.assert_allclose(pr.uv_px, q + 0.5, atol=1e-9)
        np.testing.assert_allclose(pr.d_uv_d_point, dq_dp, rtol=1e-9, atol=1e-9)
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL"):
            dq_di = np.concatenate([dq_di[..., :1] + dq_di[..., 1:2], dq_di[..., 2:4], dq_di[..., 4:5]], -1)
            dq_di = dq_di[..., : cam.params.size]
        np.testing.assert_allclose(pr.d_uv_d_params, dq_di, rtol=1e-9, atol=1e-9)
        # pycolmap's own camera model implementation (same pixel convention).
        np.testing.assert_allclose(pr.uv_px, cam.to_pycolmap().img_from_cam(P), atol=1e-9)


@pytest.mark.parametrize("model", MODELS)
def test_jacobians_against_central_differences(model, rng):
    cam = make_camera(model, rng)
    P = points_in_view(rng, 30)
    pr = cam.project(P, with_jacobians=True)
    h = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        fd = (cam.project(P + d).uv_px - cam.project(P - d).uv_px) / (2 * h)
        # Central differences: truncation O(h^2 * |f'''|) + rounding O(eps * |uv| / h) ~ 1e-7 px/m.
        np.testing.assert_allclose(pr.d_uv_d_point[..., k], fd, rtol=1e-6, atol=1e-5)
    for k in range(cam.params.size):
        hp = 1e-6 * max(1.0, abs(cam.params[k]))
        pp, pm = cam.params.copy(), cam.params.copy()
        pp[k] += hp
        pm[k] -= hp
        fd = (Camera(model, W, H, pp).project(P).uv_px - Camera(model, W, H, pm).project(P).uv_px) / (2 * hp)
        np.testing.assert_allclose(pr.d_uv_d_params[..., k], fd, rtol=1e-6, atol=1e-4)


@pytest.mark.parametrize("model", MODELS)
def test_unproject_roundtrip_and_against_references(model, rng):
    for _ in range(5):
        cam = make_camera(model, rng)
        P = points_in_view(rng, 300)
        uv = cam.project(P).uv_px
        un = cam.unproject(uv)
        assert un.valid.all() and un.converged.all() and un.residual_px.max() <= 1e-9
        # Newton converged to 1e-9 px: ray error < 1e-9 px / f ~ 1e-11 (normalised units).
        np.testing.assert_allclose(un.rays_cam, P / P[:, 2:], atol=1e-10)
        lens, intr = cam.to_mrcal()
        v = mrcal.unproject(uv - 0.5, lens, intr)
        np.testing.assert_allclose(un.rays_cam[:, :2], v[:, :2] / v[:, 2:], atol=1e-7)
        K_cv, d_cv = cam.to_opencv()
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        xy_cv = cv2.undistortPoints((uv - 0.5)[:, None], K_cv, d_cv if d_cv.size else np.zeros(4), None, None,
                                    None, crit)[:, 0]
        # OpenCV's fixed-point iteration converges more slowly; 1e-7 normalised ~ 1e-4 px.
        np.testing.assert_allclose(un.rays_cam[:, :2], xy_cv, atol=1e-7)


def test_unproject_flags_points_beyond_distortion_fold():
    # k1 < 0 strong barrel: r_d = r (1 + k1 r^2) peaks at r = 1/sqrt(-3 k1); beyond its maximum
    # distorted radius no undistorted point maps there, so the inverse does not exist.
    cam = Camera("SIMPLE_RADIAL", W, H, np.array([300.0, 320.0, 240.0, -0.3]))
    r_max = 1 / np.sqrt(0.9)
    rd_max = r_max * (1 - 0.3 * r_max**2)
    u_beyond = 320 + 300 * rd_max * np.array([0.5, 0.99, 1.01, 1.5])
    un = cam.unproject(np.c_[u_beyond, np.full(4, 240.0)])
    assert un.valid.tolist() == [True, True, False, False]
    assert np.all(np.isfinite(un.rays_cam))
    # Projection beyond the fold is flagged too, and points behind the camera.
    pr = cam.project(np.array([[0.5 * r_max, 0, 1], [1.5 * r_max, 0, 1], [0.1, 0, -1], [0, 0, 0]]))
    assert pr.valid.tolist() == [True, False, False, False]
    assert np.all(np.isfinite(pr.uv_px))


def test_projection_beyond_the_first_fold_is_invalid_where_the_map_rises_again(rng):
    # k1 < 0 < k2: r_d = r (1 - 0.4 r^2 + 0.05 r^4) rises to r^2 = 1.07, falls until r^2 = 3.73, then rises again.
    # A ray at r = 2 lands on the pixel of a ray at r ~ 0.431 (inside the image): it is beyond the fold although
    # the map increases there.
    cam = Camera("OPENCV", W, H, np.array([300.0, 300.0, 320.0, 240.0, -0.4, 0.05, 0.0, 0.0]))
    pr = cam.project(np.array([[0.431, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0], [2.5, 0.0, 1.0]]))
    assert pr.valid.tolist() == [True, True, False, False]
    assert abs(pr.uv_px[2, 0] - 440.0) < 1e-9 and cam.in_image(pr.uv_px[2])
    un = cam.unproject(pr.uv_px[2:3])
    assert un.valid[0] and abs(un.rays_cam[0, 0] - 0.4314) < 1e-4  # the pixel's ray is the one inside the disc
    # The valid disc against a dense radial scan of the map, for random (rational) models.
    s = np.linspace(0.0, 16.0, 160001)[1:]
    for _ in range(200):
        k1, k2, k3, k4, k5, k6 = rng.normal(size=6) * [0.5, 0.3, 0.1, 0.5, 0.3, 0.1]
        cam = Camera("FULL_OPENCV", W, H, np.array([300.0, 300.0, 320.0, 240.0, k1, k2, 0, 0, k3, k4, k5, k6]))
        b = 1 + k4 * s + k5 * s**2 + k6 * s**3
        r_d = np.sqrt(s) * (1 + k1 * s + k2 * s**2 + k3 * s**3) / b
        ok = np.r_[True, np.diff(r_d) > 0] & (b > 0)
        ref = np.minimum.accumulate(ok)  # valid up to the first radius where the map stops increasing
        got = cam.project(np.c_[np.sqrt(s), np.zeros_like(s), np.ones_like(s)]).valid
        assert np.count_nonzero(got != ref) <= 2  # the boundary sample itself


def test_scaled_camera_exact_in_pixel_edge_convention(rng):
    cam = make_camera("OPENCV", rng)
    half = cam.scaled(W // 2, H // 2)
    P = points_in_view(rng, 50)
    # Resizing maps pixel edges 0..W to 0..W/2, so uv scales exactly by 1/2 in our convention.
    np.testing.assert_allclose(half.project(P).uv_px, cam.project(P).uv_px / 2, atol=1e-10)
    simple = Camera("SIMPLE_RADIAL", W, H, np.array([500.0, 320.0, 240.0, 0.01]))
    aniso = simple.scaled(320, 480)
    assert aniso.model == "OPENCV" and aniso.fx == 250 and aniso.fy == 500
    np.testing.assert_allclose(aniso.project(P).uv_px, simple.project(P).uv_px * [0.5, 1.0], atol=1e-10)
    with pytest.raises(InputError):
        cam.scaled(0, 10)


def test_interop_roundtrips(rng):
    for model in MODELS:
        cam = make_camera(model, rng)
        back = Camera.from_pycolmap(cam.to_pycolmap())
        assert back.model == model and np.array_equal(back.params, cam.params)
        lens, intr = cam.to_mrcal()
        m = Camera.from_mrcal(lens, intr, W, H)
        P = points_in_view(rng, 20)
        np.testing.assert_allclose(m.project(P).uv_px, cam.project(P).uv_px, atol=1e-9)
        K_cv, d_cv = cam.to_opencv()
        o = Camera.from_opencv(K_cv, d_cv, W, H)
        np.testing.assert_allclose(o.project(P).uv_px, cam.project(P).uv_px, atol=1e-9)
    with pytest.raises(InputError):
        Camera.from_mrcal("LENSMODEL_CAHVOR", np.zeros(9), W, H)


def test_pinhole_problem_names_distortion_and_a_focal_that_is_not_positive():
    """`Camera.pinhole_problem`: None for pinholes and for distortion models whose coefficients are all zero."""
    assert Camera("PINHOLE", 64, 48, [50.0, 51.0, 32.0, 24.0]).pinhole_problem() is None
    assert Camera("SIMPLE_RADIAL", 64, 48, [50.0, 32.0, 24.0, 0.0]).pinhole_problem() is None
    assert Camera("OPENCV", 64, 48, [50.0, 51.0, 32.0, 24.0, 0.0, 0.0, 0.0, 0.0]).pinhole_problem() is None
    assert "lens distortion" in Camera("OPENCV", 64, 48, [50.0, 51.0, 32.0, 24.0, 0.0, 0.0, 1e-4, 0.0]
                                       ).pinhole_problem()
    assert "lens distortion" in Camera("SIMPLE_RADIAL", 64, 48, [50.0, 32.0, 24.0, -0.2]).pinhole_problem()
    for f in ([0.0, 51.0], [50.0, -1.0], [float("nan"), 51.0], [float("inf"), 51.0]):
        problem = Camera("PINHOLE", 64, 48, [*f, 32.0, 24.0]).pinhole_problem()
        assert problem is not None and "focal length is not positive" in problem
