"""`mvgeo.align.cloud`: the dense cloud must agree with the cameras it is returned with.

The bundle adjustment fixes only view 0's pose, so its scene may come out at another scale than the global
alignment's; depth maps re-posed without rescaling put the output cloud 1.3-2x too far from the cameras (median
relative depth error 60 % on a 256x192 llff_like run), which smeared the splat initialisation. `reposed`
rescales them onto the tracks (`depth_rescale`); `dense_cloud` recomputes them by stereo with the final cameras.
"""

import dataclasses

import numpy as np

import mvgeo.align.cloud as cloud
from mvgeo.align.api import PREVIEW, align_images
from mvgeo.align.bundle import BundleResult
from mvgeo.align.cloud import backproject_depth, depth_rescale, reposed
from mvgeo.align.pointmap_geometry import pixel_rays
from mvgeo.common.imageio import list_images
from mvgeo.sparse_model import read_sparse_model
from mvgeo.transforms import so3_exp, umeyama


def test_depth_rescale_recovers_per_view_scales_with_outliers():
    rng = np.random.default_rng(0)
    n, H, W, f = 3, 24, 32, 30.0
    cam_from_world = np.stack([np.hstack([np.eye(3), np.array([[0.1 * v], [0.0], [0.0]])]) for v in range(n)])
    depths = [rng.uniform(2.0, 5.0, size=(H, W)) for _ in range(n)]
    true = np.array([0.5, 1.0, 2.0])
    obs_view, obs_point, obs_uv, pts = [], [], [], []
    for v in range(n):
        uv = rng.uniform([0, 0], [W, H], size=(100, 2))
        z = depths[v][np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)] * true[v]
        z[:10] *= 3.0  # 10 % gross outliers: the median must ignore them
        x_cam = np.stack([(uv[:, 0] - W / 2) / f * z, (uv[:, 1] - H / 2) / f * z, z], axis=1)
        R, t = cam_from_world[v][:, :3], cam_from_world[v][:, 3]
        pts.append((x_cam - t) @ R)
        obs_view += [v] * 100
        obs_point += list(range(len(obs_point), len(obs_point) + 100))
        obs_uv.append(uv)
    scales, spread = depth_rescale(depths, cam_from_world, np.concatenate(pts), np.array(obs_view),
                                   np.array(obs_point), np.concatenate(obs_uv))
    np.testing.assert_allclose(scales, true, rtol=1e-9)  # exact data apart from the outliers
    assert np.all(spread < 1e-9)


def test_depth_rescale_leaves_views_without_tracks_alone():
    depths = [np.ones((4, 4)), np.ones((4, 4))]
    cfw = np.stack([np.hstack([np.eye(3), np.zeros((3, 1))])] * 2)
    scales, spread = depth_rescale(depths, cfw, np.array([[0.0, 0.0, 2.0]] * 3), np.array([0, 0, 0]),
                                   np.array([0, 1, 2]), np.full((3, 2), 1.5))
    assert scales[1] == 1.0 and np.isnan(spread[1])  # no observations
    assert scales[0] == 1.0 and np.isnan(spread[0])  # fewer than 5 usable observations


@dataclasses.dataclass
class _Aligned:
    cam_from_world: np.ndarray
    focal_px: np.ndarray
    pts_world: list
    depth: list


def test_reposed_puts_the_dense_points_on_a_rescaled_bundle_adjustment():
    """A BA that returns the same scene at half the scale: the re-posed cloud must follow it."""
    rng = np.random.default_rng(1)
    H, W, f, n = 12, 16, 20.0, 2
    cfw = np.stack([np.hstack([np.eye(3), np.array([[-0.5 * v], [0.0], [0.0]])]) for v in range(n)])
    depths = [rng.uniform(3.0, 6.0, size=(H, W)) for _ in range(n)]
    pts = [(pixel_rays(H, W, f) * d[..., None]) - T[:, 3] @ T[:, :3] for d, T in zip(depths, cfw, strict=True)]
    res = _Aligned(cfw, np.full(n, f), pts, depths)
    half = cfw.copy()
    half[:, :, 3] *= 0.5
    # Tracks: every pixel of both views, at the BA's (halved) scale.
    ov = np.repeat(np.arange(n), H * W)
    uv = np.tile(np.stack(np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5), -1).reshape(-1, 2), (n, 1))
    X = np.concatenate([0.5 * p.reshape(-1, 3) for p in pts])
    ba = BundleResult(half, np.full(n, f), len(X), len(X), 0.0, 0.0, 0.0, 0.0,
                      track_xyz=X, obs_view=ov, obs_point=np.arange(len(X)), obs_uv=uv)
    out, rescale = reposed(res, half, np.full(n, f), ba, 1.0)
    np.testing.assert_allclose(rescale[0], [0.5, 0.5], rtol=1e-6)
    for v in range(n):
        np.testing.assert_allclose(out.pts_world[v], 0.5 * pts[v], atol=1e-9)
    stale, none = reposed(res, half, np.full(n, f))  # without tracks: not rescaled, off by 2x
    assert none is None
    assert np.abs(stale.pts_world[1] - 0.5 * pts[1]).max() > 1.0


def _cloud_depth_error(llff6, left: int = 0, top: int = 0):
    """Align `llff6` with its true camera (views cropped by `left` / `top` px, the principal point moved with
    them), register the estimated cameras to the truth (Sim(3) on centres), map the cloud, and return the
    median relative depth error against the true depth maps, and the result."""
    from mvgeo.camera import Camera
    from mvgeo.common.imageio import read_image

    gt = read_sparse_model(llff6 / "sparse" / "0")
    cam0 = gt.camera_of(gt.names[0])
    paths = list_images(llff6 / "images")
    images = [read_image(p)[top:, left:] for p in paths]
    H, W = images[0].shape[:2]
    cam = Camera.pinhole(cam0.fx, cam0.fy, cam0.cx - left, cam0.cy - top, W, H)
    res = align_images(images, dataclasses.replace(PREVIEW, seed=0), intrinsics=cam, names=[p.name for p in paths])
    names = [im.name for im in res.sparse_model.images]
    est = {im.name: np.asarray(im.cam_from_world)[:3] for im in res.sparse_model.images}
    centre = lambda T: -T[:, :3].T @ T[:, 3]  # noqa: E731
    sim = umeyama(np.stack([centre(np.asarray(gt.image(n).cam_from_world)[:3]) for n in names]),
                  np.stack([centre(est[n]) for n in names]), with_scale=True)
    xyz_gt_frame = ((res.points_xyz - sim.t) @ sim.R) / sim.scale
    rel = []
    for n in names:
        T = np.asarray(gt.image(n).cam_from_world)[:3]
        xc = xyz_gt_frame @ T[:, :3].T + T[:, 3]
        front = xc[:, 2] > 0
        u = cam.fx * xc[front, 0] / xc[front, 2] + cam.cx
        v = cam.fy * xc[front, 1] / xc[front, 2] + cam.cy
        inside = (u >= 0) & (v >= 0) & (u < W) & (v < H)
        depth = np.load(llff6 / "depth" / (n.rsplit(".", 1)[0] + ".npy"))[top:, left:]
        z_true = depth[v[inside].astype(int), u[inside].astype(int)]
        ok = np.isfinite(z_true)
        rel.append(np.abs(xc[front][inside][ok, 2] / z_true[ok] - 1.0))
    return float(np.median(np.concatenate(rel))), res


def test_dense_cloud_lies_on_the_true_surface(llff6):
    """Known intrinsics (so that a focal error cannot distort the comparison)."""
    med, res = _cloud_depth_error(llff6)
    # Measured 2026-11-21 on these noisy (sigma 25/255) images: 0.028 with the dense stereo on the final
    # cameras; 0.124 (voxel thinning) from the global alignment's depth maps rescaled onto the tracks;
    # 0.6 on the 8-view run that showed the scale bug. 0.07 fails a return to the alignment's depth maps.
    assert med < 0.07, f"median relative depth error of the dense cloud {med:.3f}"
    # The stereo depths agree with the bundle-adjusted tracks of the same cameras (median ratio per view;
    # measured within 0.5 % of 1).
    ratio = np.array(res.stats.dense_stereo.track_depth_ratio)
    assert np.all(np.abs(ratio - 1.0) < 0.02), ratio


def test_the_dense_cloud_uses_a_known_off_centre_principal_point(llff6):
    """Views cropped unevenly (the principal point 12 / 8 px off the centre): the stereo triangulates with the
    calibration's principal point, so the cloud is as close to the surface as the uncropped views' is."""
    med, _ = _cloud_depth_error(llff6, left=24, top=16)
    full, _ = _cloud_depth_error(llff6)
    assert med < max(1.5 * full, 0.04), (med, full)


def test_without_the_stereo_the_cloud_lies_on_the_output_cameras_rays(llff6, monkeypatch):
    """Dense stereo off, a known principal point 12 / 8 px off the centre (views cropped unevenly): each view's
    points, as the co-visibility pruning gets them, project back through that view's output camera onto the
    centres of their own pixels (the alignment's depth maps were measured on rays through the grid's centre)."""
    from mvgeo.camera import Camera
    from mvgeo.common.imageio import read_image

    seen = []
    real = cloud.covisibility_keep

    def spy(pts_world, depth, conf, cam_from_world, K, **kw):
        seen.append((pts_world, depth, cam_from_world, K))
        return real(pts_world, depth, conf, cam_from_world, K, **kw)

    monkeypatch.setattr(cloud, "covisibility_keep", spy)
    gt = read_sparse_model(llff6 / "sparse" / "0")
    cam0 = gt.camera_of(gt.names[0])
    left, top = 24, 16
    paths = list_images(llff6 / "images")
    images = [read_image(p)[top:, left:] for p in paths]
    H, W = images[0].shape[:2]
    cam = Camera.pinhole(cam0.fx, cam0.fy, cam0.cx - left, cam0.cy - top, W, H)
    config = dataclasses.replace(PREVIEW, seed=0,
                                 dense_stereo=dataclasses.replace(PREVIEW.dense_stereo, enabled=False))
    align_images(images, config, intrinsics=cam, names=[p.name for p in paths])
    ((pts, depth, cams, K),) = seen
    Hg, Wg = depth[0].shape
    assert abs(K[0][0, 2] - (cam.cx * Wg / W)) < 1e-9 and abs(K[0][0, 2] - Wg / 2) > 1.0  # off the centre
    for v in range(len(pts)):
        x = pts[v].reshape(-1, 3) @ cams[v][:, :3].T + cams[v][:, 3]
        ok = np.isfinite(x).all(axis=1) & (x[:, 2] > 0)
        u = K[v][0, 0] * x[ok, 0] / x[ok, 2] + K[v][0, 2]
        w = K[v][1, 1] * x[ok, 1] / x[ok, 2] + K[v][1, 2]
        rows, cols = np.divmod(np.flatnonzero(ok), Wg)
        np.testing.assert_allclose(u, cols + 0.5, atol=1e-6)
        np.testing.assert_allclose(w, rows + 0.5, atol=1e-6)


def test_a_view_the_stereo_leaves_empty_keeps_the_alignment_depth(llff6, monkeypatch):
    real = cloud.stereo_depths

    def first_view_empty(*args, **kwargs):
        out = real(*args, **kwargs)
        out.depth[0] = np.full_like(out.depth[0], np.nan)
        out.conf[0] = np.ones_like(out.conf[0])
        return out

    monkeypatch.setattr(cloud, "stereo_depths", first_view_empty)
    res = align_images(list_images(llff6 / "images"), dataclasses.replace(PREVIEW, seed=0))
    first = res.sparse_model.images[0].name
    assert res.stats.dense_stereo.views_with_alignment_depth == [first]
    assert res.stats.dense_stereo.fraction_with_depth[0] == 0.0
    # The view still contributes points: project the cloud into it and count those in front and inside.
    T = np.asarray(res.sparse_model.images[0].cam_from_world)[:3]
    cam = res.sparse_model.camera_of(first)
    x = res.points_xyz @ T[:, :3].T + T[:, 3]
    u = cam.params[0] * x[:, 0] / x[:, 2] + cam.params[2]
    assert np.count_nonzero((x[:, 2] > 0) & (u >= 0) & (u < cam.width)) > 100


def test_backproject_depth_matches_the_pixel_loop(rng):
    H, W = 5, 7
    K = np.array([[6.0, 0.0, 3.2], [0.0, 5.5, 2.4], [0.0, 0.0, 1.0]])
    depth = rng.uniform(1.0, 3.0, (H, W))
    depth[1, 2] = np.nan
    R = so3_exp(np.array([0.1, -0.2, 0.3]))
    T = np.c_[R, [0.5, -0.1, 2.0]]
    pts = backproject_depth(depth, K, T)
    for r in range(H):
        for c in range(W):
            x_cam = depth[r, c] * np.linalg.solve(K, [c + 0.5, r + 0.5, 1.0])  # pixel centre (c + 0.5, r + 0.5)
            want = R.T @ (x_cam - T[:, 3])
            if np.isnan(depth[r, c]):
                assert np.isnan(pts[r, c]).all()
            else:
                np.testing.assert_allclose(pts[r, c], want, rtol=1e-12, atol=1e-12)
