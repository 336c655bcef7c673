"""Multi-view geometry of the renderer: depth, poses and the pixel convention agree.

The proof (issue 3): a pixel of view i lifted with its depth and projected into
view j lands within 0.5 px of where view j sees that surface, checked with view
j's depth. Also: the ground-truth cameras round-trip through pycolmap and
pycolmap's projection agrees with ours.
"""

from __future__ import annotations

import numpy as np
import pytest

from data_synth import SceneRenderer, load_scene, rig_views
from data_synth.dataset import sparse_model_of
from data_synth.intrinsics import camera_from_spec
from mvgeo.camera import Camera
from mvgeo.common.deps import pycolmap
from mvgeo.sparse_model import read_sparse_model, write_sparse_model


def _lift(depth: np.ndarray, cam: Camera, cam_from_world: np.ndarray, rows, cols) -> np.ndarray:
    """World points of pixel centres (row, col) with z-depth (reference: plain pinhole algebra)."""
    u, v = cols + 0.5, rows + 0.5
    z = depth[rows, cols].astype(np.float64)
    x_cam = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], axis=1)
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    return (x_cam - t) @ R  # R^T (x - t)


def _project(points: np.ndarray, cam: Camera, cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = points @ cam_from_world[:, :3].T + cam_from_world[:, 3]
    uv = np.stack([cam.fx * x[:, 0] / x[:, 2] + cam.cx, cam.fy * x[:, 1] / x[:, 2] + cam.cy], axis=1)
    return uv, x[:, 2]


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample at continuous pixel coords (pixel (r, c) centre = (c + 0.5, r + 0.5))."""
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    h, w = img.shape
    x0c, y0c = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
    a, b = img[y0c, x0c], img[y0c, x0c + 1]
    c, d = img[y0c + 1, x0c], img[y0c + 1, x0c + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def _reprojection_errors_px(spec, *, pp_shift_px: float = 0.0) -> np.ndarray:
    """For every pair (i, j): pixel errors of view-i pixels re-found in view j through view j's depth.

    A point X lifted from view i projects to q in view j with depth z. On a planar
    surface inverse depth is exactly affine in (u, v), so view j's inverse depth map,
    sampled bilinearly at q, must equal 1/z; the residual divided by the local
    inverse-depth gradient is the distance in pixels (along the gradient) between q and
    where view j sees X. Only planar neighbourhoods are used (the 3x3 normals of view j
    around q all equal: one facet), occluded points are skipped.
    """
    renderer = SceneRenderer.from_spec(spec)
    cam = camera_from_spec(spec.camera, tuple(spec.render.size))
    views = rig_views(spec.rig)
    renders = [renderer.render(cam, v.cam_from_world, supersample=1, depth=True, normals=True) for v in views]
    cam_assumed = Camera("PINHOLE", cam.width, cam.height,
                         np.array([cam.fx, cam.fy, cam.cx + pp_shift_px, cam.cy + pp_shift_px]))
    errors = []
    for i, vi in enumerate(views):
        d_i = renders[i].depth.astype(np.float64)
        rows, cols = np.nonzero(np.isfinite(d_i))
        X = _lift(d_i, cam_assumed, vi.cam_from_world, rows, cols)
        for j, vj in enumerate(views):
            if i == j:
                continue
            inv_j = 1.0 / renders[j].depth.astype(np.float64)  # 0 on a miss
            n_j = renders[j].normals.astype(np.float64)
            q, z = _project(X, cam_assumed, vj.cam_from_world)
            inside = (q[:, 0] > 1.5) & (q[:, 0] < cam.width - 1.5) & (q[:, 1] > 1.5) & (q[:, 1] < cam.height - 1.5)
            q, z = q[inside], z[inside]
            c, r = np.floor(q[:, 0]).astype(int), np.floor(q[:, 1]).astype(int)
            offsets = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)]
            normals = np.stack([n_j[r + dr, c + dc] for dr, dc in offsets], axis=1)
            planar = np.all(np.abs(normals - normals[:, 4:5]).max(axis=2) < 1e-4, axis=1)
            planar &= np.all(np.abs(normals).sum(axis=2) > 0, axis=1)  # all hit
            patch = np.stack([inv_j[r + dr, c + dc] for dr, dc in offsets], axis=1)
            g = np.hypot((patch[:, 5] - patch[:, 3]) / 2, (patch[:, 7] - patch[:, 1]) / 2)
            sampled = _bilinear(inv_j, q)
            visible = np.abs(sampled * z - 1) < 0.05  # occluded points are off by far more
            keep = planar & visible & (g > 1e-4 / z)  # a measurable inverse-depth slope
            errors.append(np.abs(sampled[keep] - 1 / z[keep]) / g[keep])
    return np.concatenate(errors)


def test_depth_reprojects_within_half_pixel(tiny_scene_file):
    spec = load_scene(tiny_scene_file)
    err = _reprojection_errors_px(spec)
    assert err.size > 2000  # a large part of every image is checked, not a handful of pixels
    # The acceptance bound is 0.5 px. With exact geometry the residual is float32 ray-casting
    # noise only (inverse depth is affine on a plane, so bilinear sampling is exact): measured
    # max ~3e-4 px, so 0.01 px leaves a 30x margin and is still 50x tighter than required.
    assert np.max(err) < 0.01


def test_half_pixel_convention_error_is_detected(tiny_scene_file):
    # The same check with the principal point off by (0.5, 0.5) px (OpenCV's pixel-centre
    # convention instead of ours) must fail it. A principal-point error shared by all views
    # is largely absorbed (it acts like a small common rotation), so the residual is ~0.08 px
    # rather than 0.5 px, but it is > 100x the correct residual: the test has power.
    spec = load_scene(tiny_scene_file)
    err = _reprojection_errors_px(spec, pp_shift_px=0.5)
    assert np.median(err) > 0.03


def test_gt_cameras_round_trip_through_pycolmap(tiny_scene_file, tmp_path):
    spec = load_scene(tiny_scene_file)
    views = rig_views(spec.rig)
    model = sparse_model_of(spec, views)
    write_sparse_model(tmp_path / "sparse", model, binary=False)
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse"))
    assert rec.num_images() == len(views)
    back = read_sparse_model(tmp_path / "sparse")
    cam = back.cameras[1]
    assert cam.model == "PINHOLE"
    np.testing.assert_allclose(cam.params, model.cameras[1].params, rtol=0, atol=1e-9)
    for v in views:
        # COLMAP text stores 17 significant digits: a round trip is exact to ~1e-15.
        np.testing.assert_allclose(back.image(v.name + ".png").cam_from_world, v.cam_from_world, atol=1e-12)
    # pycolmap's own projection of a lifted pixel lands on that pixel (conventions agree).
    renderer = SceneRenderer.from_spec(spec)
    camera = camera_from_spec(spec.camera, tuple(spec.render.size))
    depth = renderer.render(camera, views[0].cam_from_world, supersample=1, depth=True).depth
    rows, cols = np.nonzero(np.isfinite(depth))
    X = _lift(depth, camera, views[0].cam_from_world, rows, cols)
    image = next(im for im in rec.images.values() if im.name == views[0].name + ".png")
    pc_cam = rec.cameras[image.camera_id]
    x_cam = np.asarray(image.cam_from_world().matrix()) @ np.hstack([X, np.ones((len(X), 1))]).T
    uv = np.asarray(pc_cam.img_from_cam(x_cam.T))
    # float64 algebra on both sides: agreement to 1e-6 px.
    np.testing.assert_allclose(uv, np.stack([cols + 0.5, rows + 0.5], axis=1), atol=1e-6)


@pytest.mark.parametrize("rig", ["forward", "ring", "sphere"])
def test_builtin_rigs_look_at_their_target(rig):
    from data_synth.spec import RigSpec

    spec = RigSpec(type=rig, views=12, rotation_jitter_deg=0.0, position_jitter=0.0, depth_jitter=0.0,
                   look_at=(0.5, 4.0, 0.8))
    for v in rig_views(spec):
        R, t = v.cam_from_world[:, :3], v.cam_from_world[:, 3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        x = R @ np.array(spec.look_at) + t
        assert x[2] > 0
        np.testing.assert_allclose(x[:2], 0, atol=1e-9)  # target on the optical axis
        # World up appears upwards: a point above the target has smaller camera y.
        above = R @ (np.array(spec.look_at) + np.array([0, 0, 0.1])) + t
        assert above[1] / above[2] < 0


def test_ring_rig_places_cameras_as_documented():
    # radius is horizontal (perpendicular to up), height is along up; the first view sits at azimuth
    # start_deg from up x (1, 0, 0) (+y for up = +z) and the ring runs counter-clockwise about up.
    from data_synth.spec import RigSpec

    spec = RigSpec(type="ring", views=4, radius=2.0, height=0.5, start_deg=0.0, look_at=(1.0, -1.0, 0.3),
                   position_jitter=0.0, rotation_jitter_deg=0.0)
    centres = np.array([-v.cam_from_world[:, :3].T @ v.cam_from_world[:, 3] for v in rig_views(spec)])
    offsets = centres - np.array(spec.look_at)
    np.testing.assert_allclose(offsets, [[0, 2, 0.5], [-2, 0, 0.5], [0, -2, 0.5], [2, 0, 0.5]], atol=1e-12)
