"""Multi-view Noise2Noise: the warp against a per-pixel loop, a plane scene seen by several cameras,
occlusion masking, neighbour choice and a short training run."""

import numpy as np
import pytest

from denoise.multiview_n2n import MultiViewConfig, multiview_targets, neighbour_views, train_multiview_n2n, warp_view
from denoise.n2v import N2VConfig
from denoise.self_supervised import denoise_one_pass
from denoise.unet import UNetConfig
from mvgeo.common.errors import ConfigError, InputError
from tests.denoise._synth import add_noise, psnr

PLANE_Z = 4.0


def _look(cx: float, cy: float, yaw_deg: float = 0.0) -> np.ndarray:
    """cam_from_world of a camera at (cx, cy, 0) turned by yaw about the y axis, looking along +z."""
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    C = np.array([cx, cy, 0.0])
    return np.hstack([R, (-R @ C)[:, None]])


def _texture(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Smooth RGB texture of the plane z = PLANE_Z (values in [0.15, 0.85])."""
    return np.stack([0.5 + 0.35 * np.sin(3 * X) * np.cos(2 * Y), 0.5 + 0.35 * np.cos(2.5 * X + Y),
                     0.5 + 0.35 * np.sin(1.7 * Y - X)], axis=-1)


def _render_plane(K: np.ndarray, cam: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Clean image and z-depth of the textured plane z = PLANE_Z."""
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    rays_c = np.stack([cols + 0.5, rows + 0.5, np.ones_like(cols)], -1) @ np.linalg.inv(K).T
    R, t = cam[:, :3], cam[:, 3]
    C = -R.T @ t
    rays_w = rays_c @ R  # R^T d
    s = (PLANE_Z - C[2]) / rays_w[..., 2]
    P = C + s[..., None] * rays_w
    depth = ((P - C) @ R.T)[..., 2]
    return _texture(P[..., 0], P[..., 1]).astype(np.float32), depth


def _warp_loop(image_j, depth_i, K_i, cam_i, K_j, cam_j, depth_j, tol):
    """Slow reference: one pixel at a time, bilinear weights written out."""
    h, w = depth_i.shape
    hj, wj = image_j.shape[:2]
    out = np.zeros((h, w, image_j.shape[2]), np.float64)
    valid = np.zeros((h, w), bool)
    for r in range(h):
        for c in range(w):
            d = depth_i[r, c]
            if not np.isfinite(d) or d <= 0:
                continue
            x_i = d * np.linalg.solve(K_i, [c + 0.5, r + 0.5, 1.0])
            X = cam_i[:, :3].T @ (x_i - cam_i[:, 3])
            x_j = cam_j[:, :3] @ X + cam_j[:, 3]
            if x_j[2] <= 0:
                continue
            u, v, _ = K_j @ (x_j / x_j[2])
            cj, rj = u - 0.5, v - 0.5
            if not (-1e-6 <= cj <= wj - 1 + 1e-6 and -1e-6 <= rj <= hj - 1 + 1e-6):
                continue
            dj = depth_j[int(round(rj)), int(round(cj))]
            if not (np.isfinite(dj) and abs(dj - x_j[2]) <= tol * x_j[2]):
                continue
            cj, rj = min(max(cj, 0.0), wj - 1.0), min(max(rj, 0.0), hj - 1.0)
            c0, r0 = min(int(np.floor(cj)), wj - 2), min(int(np.floor(rj)), hj - 2)
            fc, fr = cj - c0, rj - r0
            out[r, c] = ((1 - fr) * ((1 - fc) * image_j[r0, c0] + fc * image_j[r0, c0 + 1])
                         + fr * ((1 - fc) * image_j[r0 + 1, c0] + fc * image_j[r0 + 1, c0 + 1]))
            valid[r, c] = True
    return out, valid


K = np.array([[40.0, 0, 16.0], [0, 40.0, 12.0], [0, 0, 1]])


def test_warp_matches_loop_and_reproduces_the_plane(rng):
    cam_i, cam_j = _look(0, 0), _look(0.4, -0.1, yaw_deg=4)
    img_i, d_i = _render_plane(K, cam_i, 24, 32)
    img_j, d_j = _render_plane(K, cam_j, 24, 32)
    d_i = d_i.copy()
    d_i[3, 5] = np.nan  # unknown depth: never valid
    warped, valid = warp_view(img_j, d_i, K, cam_i, K, cam_j, d_j, depth_rel_tol=0.01)
    ref, ref_valid = _warp_loop(img_j, d_i, K, cam_i, K, cam_j, d_j, 0.01)
    np.testing.assert_array_equal(valid, ref_valid)
    # cv2.remap's bilinear weights are fixed-point (1/32 px): a few 1e-3 of a smooth texture.
    np.testing.assert_allclose(warped[valid], ref[valid], atol=5e-3)
    assert not valid[3, 5] and valid.mean() > 0.6  # the shifted view still covers most of view i
    # The warped neighbour is view i's own image (a plane: exact geometry; bilinear error only).
    assert np.abs(warped[valid] - img_i[valid]).max() < 0.02
    assert (warped[~valid] == 0).all()


def test_depth_consistency_masks_occlusions():
    cam_i, cam_j = _look(0, 0), _look(0.3, 0)
    img_j, d_j = _render_plane(K, cam_j, 24, 32)
    _, d_i = _render_plane(K, cam_i, 24, 32)
    occluded = d_j.copy()
    occluded[:, :12] *= 0.5  # something in front of the plane in the left part of view j
    _, valid_free = warp_view(img_j, d_i, K, cam_i, K, cam_j, d_j)
    _, valid_occ = warp_view(img_j, d_i, K, cam_i, K, cam_j, occluded)
    _, valid_nodepth = warp_view(img_j, d_i, K, cam_i, K, cam_j, None)
    assert valid_occ.sum() < valid_free.sum() - 100
    np.testing.assert_array_equal(valid_nodepth, valid_free)  # nothing else differs on a plane
    # The masked pixels are exactly those whose projection lands in the occluded columns.
    ref_occ = _warp_loop(img_j, d_i, K, cam_i, K, cam_j, occluded, 0.01)[1]
    np.testing.assert_array_equal(valid_occ, ref_occ)


def test_neighbour_views_by_axis_angle():
    cams = np.stack([_look(0, 0, 0), _look(0, 0, 10), _look(0, 0, 25), _look(0, 0, 90)])  # 90: 65 deg from the nearest
    assert neighbour_views(cams, neighbours=2, max_angle_deg=60) == [[1, 2], [0, 2], [1, 0], []]
    with pytest.raises(ConfigError, match="neighbours"):
        MultiViewConfig(neighbours=0)


def test_multiview_n2n_denoises_a_plane_seen_five_times(rng):
    # Five views of the textured plane, sigma 25/255. Each view's target averages up to 4 warped
    # neighbours; 300 steps of 4 patches of 16 px on a width-8, depth-2 UNet (4-8 s).
    cams = [_look(0.15 * k, 0.05 * k, yaw_deg=2 * k) for k in range(5)]
    renders = [_render_plane(K, c, 48, 64) for c in cams]
    clean = [r[0] for r in renders]
    depths = [r[1] for r in renders]
    noisy = [add_noise(rng, c, 25 / 255) for c in clean]
    targets = multiview_targets(noisy, np.stack([K] * 5), np.stack(cams), depths, MultiViewConfig())
    assert all(cnt.max() == 4 for _, cnt in targets)
    cfg = N2VConfig(unet=UNetConfig(width=8, depth=2), steps=300, batch_size=4, patch_px=16)
    model = train_multiview_n2n(noisy, targets, cfg, seed=0)
    assert not model.blind_spot
    out = denoise_one_pass(model, noisy)
    gain = np.mean([psnr(o, c) - psnr(n, c) for o, n, c in zip(out, noisy, clean, strict=True)])
    # Measured with this fixture: +8.0 dB (the targets themselves: about +8 dB on the 90-100 %
    # of pixels they cover; N2V on these images at 300 steps of 32 px patches: +8.2 dB). 5 dB
    # fails an identity (0 dB), a network that does not learn (the untrained start loses
    # about 1.4 dB) or blurred, misaligned targets, and leaves room for BLAS differences.
    assert gain > 5.0, gain
    with pytest.raises(InputError, match="no pixel"):
        train_multiview_n2n(noisy, [(t, np.zeros_like(c)) for t, c in targets], cfg)


def test_warp_never_mixes_an_occluders_colour_into_a_valid_pixel():
    # A textured plane (world z = 5) seen by two cameras; in view j a fronto occluder at depth 3 hides part of it.
    # Every pixel the warp keeps must be the plane's colour: the depth test covers each of the four pixels the
    # bilinear sample mixes (with the nearest one alone, 0.6 % of the valid pixels, along the occluder's edge,
    # took 19-31 % of the occluder's colour).
    H, W, f = 96, 128, 100.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])

    def render(P, occluder=None):
        R, t = P[:, :3], P[:, 3]
        C = -R.T @ t
        rows, cols = np.mgrid[0:H, 0:W].astype(float)
        d_cam = np.stack([(cols + 0.5 - W / 2) / f, (rows + 0.5 - H / 2) / f, np.ones_like(cols)], -1)
        d_w = d_cam @ R
        lam = (5.0 - C[2]) / d_w[..., 2]
        X = C + lam[..., None] * d_w
        img = np.stack([0.5 + 0.3 * np.sin(1.3 * X[..., 0]) * np.cos(0.9 * X[..., 1]),
                        0.5 + 0.3 * np.cos(2.1 * X[..., 0] + X[..., 1]), 0.5 + 0.2 * np.sin(1.7 * X[..., 1])], -1)
        z = lam * d_cam[..., 2]
        if occluder is not None:
            r0, r1, c0, c1 = occluder
            img[r0:r1, c0:c1] = 0.0
            z[r0:r1, c0:c1] = ((3.0 - C[2]) / d_w[..., 2] * d_cam[..., 2])[r0:r1, c0:c1]
        return img.astype(np.float32), z

    a = np.radians(5.0)
    Rj = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Pi = np.hstack([np.eye(3), np.zeros((3, 1))])
    Pj = np.hstack([Rj, (-Rj @ np.array([0.4, -0.1, 0.2]))[:, None]])
    img_i, z_i = render(Pi)
    img_j, z_j = render(Pj, occluder=(30, 60, 40, 80))
    warped, valid = warp_view(img_j, z_i, K, Pi, K, Pj, z_j, depth_rel_tol=0.01)
    assert 0.7 < valid.mean() < 0.9  # the occluded and out-of-view pixels are left out, the rest kept
    assert np.abs(warped - img_i)[valid].max() < 0.005  # bilinear sampling of a smooth texture
