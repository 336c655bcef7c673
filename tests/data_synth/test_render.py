"""Renderer against analytic references: pixel convention, z-depth, coverage, normals, distortion."""

from __future__ import annotations

import numpy as np
import pytest

from data_synth.geometry import PlacedMesh, build_mesh
from data_synth.intrinsics import camera_rays, sample_positions
from data_synth.render import SceneRenderer
from data_synth.rigs import look_at_cam_from_world
from data_synth.spec import LightingSpec, ObjectSpec, TextureSpec
from mvgeo.camera import Camera
from mvgeo.common.deps import cv2

IDENTITY = np.hstack([np.eye(3), np.zeros((3, 1))])  # camera at the origin looking along +z
FLAT = TextureSpec(pattern="constant", colors=((0.5, 0.5, 0.5),))


def _plane_facing_camera(z: float, x_min: float, *, width: float = 40.0) -> ObjectSpec:
    """A plane z = const (normal -z after flipping) covering x >= x_min."""
    return ObjectSpec(name="p", shape="plane", texture="t", size=(width, width),
                      translate=(x_min + width / 2, 0.0, z)).validated(key="p", path=None)


UNLIT = LightingSpec(mode="unlit")


def _renderer(objs, *, lighting=UNLIT, background=(0.0, 0.0, 0.0)):
    meshes = [build_mesh(o) for o in objs]
    return SceneRenderer(meshes, [FLAT] * len(meshes), lighting=lighting, background=background)


def test_pixel_centres_follow_our_convention():
    # Samples of pixel (row, col) lie at (col + (j + 0.5)/n, row + (i + 0.5)/n).
    s = sample_positions((3, 2), 2)
    assert s.shape == (2, 2, 3, 2, 2)
    np.testing.assert_array_equal(s[0, 0, 0, 0], [0.25, 0.25])
    np.testing.assert_array_equal(s[1, 1, 2, 0], [2.25, 1.75])
    np.testing.assert_array_equal(sample_positions((3, 2), 1)[1, 0, 2, 0], [2.5, 1.5])


@pytest.mark.parametrize(("edge_u", "expected"), [(20.0, [0.0, 1.0, 1.0]), (20.25, [0.0, 0.75, 1.0]),
                                                  (20.5, [0.0, 0.5, 1.0])])
def test_coverage_of_an_edge_at_known_pixel_position(edge_u, expected):
    # A plane edge projecting to u = edge_u: with 4x4 samples at offsets 1/8, 3/8, ... the
    # coverage of pixel column 20 is the exact fraction of sample columns right of the edge.
    # An off-by-half-pixel convention would shift every value by 0.5.
    cam = Camera("PINHOLE", 40, 8, np.array([50.0, 50.0, 20.0, 4.0]))
    z = 5.0
    x_edge = (edge_u - cam.cx) / cam.fx * z
    r = _renderer([_plane_facing_camera(z, x_edge)])
    out = r.render(cam, IDENTITY, supersample=4, alpha=True)
    np.testing.assert_allclose(out.alpha[4, 19:22], expected, atol=1e-6)


def test_depth_is_z_not_ray_length():
    # A fronto-parallel plane at z = 3 has depth exactly 3 everywhere (float32: 3 ulp).
    cam = Camera("PINHOLE", 32, 24, np.array([20.0, 20.0, 16.0, 12.0]))
    r = _renderer([_plane_facing_camera(3.0, -20.0)])
    out = r.render(cam, IDENTITY, supersample=2, depth=True, normals=True)
    np.testing.assert_allclose(out.depth, 3.0, rtol=1e-6)
    # Normals face the camera (camera frame: -z).
    np.testing.assert_allclose(out.normals.reshape(-1, 3), np.tile([0, 0, -1.0], (32 * 24, 1)), atol=1e-6)


def test_misses_give_inf_depth_background_and_zero_alpha():
    cam = Camera("PINHOLE", 16, 12, np.array([10.0, 10.0, 8.0, 6.0]))
    r = _renderer([_plane_facing_camera(3.0, 100.0)], background=(0.2, 0.4, 0.6))  # plane out of view
    out = r.render(cam, IDENTITY, supersample=2, depth=True, alpha=True, normals=True)
    assert np.all(np.isinf(out.depth))
    np.testing.assert_allclose(out.rgb, np.broadcast_to([0.2, 0.4, 0.6], out.rgb.shape), atol=1e-7)
    assert np.all(out.alpha == 0)
    assert np.all(out.normals == 0)


def test_only_requested_outputs_are_computed():
    cam = Camera("PINHOLE", 16, 12, np.array([10.0, 10.0, 8.0, 6.0]))
    r = _renderer([_plane_facing_camera(3.0, -20.0)])
    out = r.render(cam, IDENTITY, supersample=2)
    assert out.depth is None and out.alpha is None and out.normals is None


def test_odd_and_even_supersampling_agree_on_depth():
    # n odd reuses the centre sample, n even casts pixel-centre rays: the same depth.
    cam = Camera("PINHOLE", 24, 18, np.array([20.0, 20.0, 12.0, 9.0]))
    obj = ObjectSpec(name="s", shape="sphere", texture="t", radius=1.0,
                     translate=(0.2, 0.1, 4.0)).validated(key="s", path=None)
    r = _renderer([obj])
    d3 = r.render(cam, IDENTITY, supersample=3, depth=True).depth
    d2 = r.render(cam, IDENTITY, supersample=2, depth=True).depth
    np.testing.assert_array_equal(np.isinf(d3), np.isinf(d2))
    np.testing.assert_allclose(d3[np.isfinite(d3)], d2[np.isfinite(d2)], rtol=1e-6)


def test_lambert_shading_matches_formula():
    # Plane facing the camera (normal -z), light direction towards (0, 0, -1) rotated by 60 deg:
    # colour = albedo * (ambient + intensity * cos 60).
    light = (0.0, -np.sin(np.pi / 3), -np.cos(np.pi / 3))
    lighting = LightingSpec(mode="lambert", direction=light, ambient=0.2, intensity=0.6)
    cam = Camera("PINHOLE", 8, 6, np.array([10.0, 10.0, 4.0, 3.0]))
    r = _renderer([_plane_facing_camera(3.0, -20.0)], lighting=lighting)
    out = r.render(cam, IDENTITY, supersample=1)
    np.testing.assert_allclose(out.rgb, 0.5 * (0.2 + 0.6 * 0.5), atol=1e-6)


def test_distorted_rays_reproject_with_opencv():
    # OPENCV camera: the ray of pixel (u, v), projected with cv2.projectPoints (whose pixel
    # centre is (0, 0): subtract 0.5 from our cx, cy and add it back), returns to (u, v).
    cam = Camera("OPENCV", 64, 48, np.array([50.0, 52.0, 32.0, 24.0, -0.2, 0.05, 0.001, -0.002]))
    uv = sample_positions((64, 48), 1).reshape(-1, 2)
    dirs, valid = camera_rays(cam, uv)
    assert valid.all()
    K_cv = np.array([[cam.fx, 0, cam.cx - 0.5], [0, cam.fy, cam.cy - 0.5], [0, 0, 1.0]])
    proj, _ = cv2.projectPoints(dirs.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_cv, cam.params[4:8])
    # Newton undistortion converges to 1e-12 in normalised units: 1e-9 px is ample.
    np.testing.assert_allclose(proj.reshape(-1, 2) + 0.5, uv, atol=1e-8)


def test_placed_mesh_local_frame_round_trip():
    obj = ObjectSpec(name="b", shape="box", texture="t", size=(1.0, 2.0, 3.0), translate=(1.0, -2.0, 0.5),
                     rotate_deg=(10.0, 20.0, 30.0), scale=1.5).validated(key="b", path=None)
    mesh: PlacedMesh = build_mesh(obj)
    world = mesh.vertices_world().astype(np.float32)
    np.testing.assert_allclose(mesh.local_from_world(world), mesh.vertices_local, atol=1e-5)  # float32


def test_look_at_roll_and_degenerate_up():
    from mvgeo.common.errors import DegenerateGeometryError

    pose = look_at_cam_from_world(np.zeros(3), np.array([0.0, 0.0, 5.0]), np.array([0.0, -1.0, 0.0]))
    np.testing.assert_allclose(pose[:, :3], np.eye(3), atol=1e-12)  # OpenCV axes: y down = -up
    with pytest.raises(DegenerateGeometryError):
        look_at_cam_from_world(np.zeros(3), np.array([0.0, 0.0, 5.0]), np.array([0.0, 0.0, 1.0]))


def test_smooth_normals_stay_outward_at_silhouettes():
    # A closed smooth (interpolated-normal) sphere: every hit's shading normal points out of the sphere,
    # also where a grazing ray at the silhouette sees a face whose vertex normals already turn away from
    # the camera. Turned inwards there, the rim's shading would depend on the view (Lambertian: it must not).
    obj = ObjectSpec(name="s", shape="sphere", texture="t", radius=1.0, resolution=8,
                     translate=(0.0, 0.0, 0.0)).validated(key="s", path=None)
    r = _renderer([obj])
    cam = Camera("PINHOLE", 64, 64, np.array([80.0, 80.0, 32.0, 32.0]))
    rims = 0
    for position in ([0.0, -4.0, 0.3], [3.0, 2.5, -1.0], [-2.0, 0.5, 3.5]):
        pose = look_at_cam_from_world(np.array(position), np.zeros(3), np.array([0.0, 0.0, 1.0]))
        R = pose[:, :3]
        centre = -R.T @ pose[:, 3]
        dirs_cam, _ = camera_rays(cam, sample_positions((64, 64), 3).reshape(-1, 2))
        hits = r.cast(centre, dirs_cam @ R, normals=True)
        radial = hits.points_world[hits.hit] / np.linalg.norm(hits.points_world[hits.hit], axis=1, keepdims=True)
        outward = np.sum(hits.normals_world[hits.hit] * radial, axis=1)
        # Smooth normals of an 8-segment sphere are within ~25 degrees of the radial direction.
        assert outward.min() > 0.8
        rims += int(np.sum(np.sum(hits.normals_world[hits.hit] * (dirs_cam @ R)[hits.hit], axis=1) > 0))
    assert rims > 0  # the views do have grazing hits whose (outward) shading normal faces away from the camera
