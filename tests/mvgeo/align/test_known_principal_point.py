"""Known intrinsics with the principal point off the image centre (and fx != fy): the bundle adjustment, the
pair checks and PnP see the matches through `mvgeo.align.solve.ideal_pixels`, the same rays in a camera with
the principal point at the centre and square pixels."""

import numpy as np
import pytest

from mvgeo.align.api import PREVIEW, align_images
from mvgeo.align.solve import ideal_matches, ideal_pixels
from mvgeo.camera import Camera
from mvgeo.common.imageio import list_images, read_image
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


def test_ideal_pixels_are_the_same_rays(rng):
    W, H = 320, 240
    K = np.array([[410.0, 0.0, 171.3], [0.0, 395.0, 108.9], [0.0, 0.0, 1.0]])
    uv = rng.uniform([0, 0], [W, H], size=(50, 2))
    rays = (np.linalg.inv(K) @ np.c_[uv, np.ones(50)].T).T
    K_ideal = np.array([[410.0, 0.0, W / 2], [0.0, 410.0, H / 2], [0.0, 0.0, 1.0]])
    ideal = ideal_pixels(uv, K, (W, H))
    rays_ideal = (np.linalg.inv(K_ideal) @ np.c_[ideal, np.ones(50)].T).T
    np.testing.assert_allclose(rays_ideal, rays, atol=1e-12)
    matches = [(0, 1, np.hstack([uv, uv[::-1]]))]
    (i, j, out), = ideal_matches(matches, np.stack([K, K]), (W, H))
    np.testing.assert_allclose(out, np.hstack([ideal, ideal[::-1]]))
    assert ideal_matches(matches, None, (W, H))[0][2] is matches[0][2]  # unknown intrinsics: as they are


def test_an_off_centre_principal_point_is_used(llff6):
    """The views cropped unevenly (24 px on the left, 16 on top): the principal point lies 12 and 8 px off
    the centre. Aligned with that camera given, the poses are as accurate as the uncropped views'."""
    gt = read_sparse_model(llff6 / "sparse" / "0")
    cam = gt.camera_of(gt.names[0])
    paths = list_images(llff6 / "images")
    crops = [read_image(p)[16:, 24:] for p in paths]
    H, W = crops[0].shape[:2]
    cropped = Camera.pinhole(cam.fx, cam.fy, cam.cx - 24, cam.cy - 16, W, H)
    assert abs(cropped.cx - W / 2) == pytest.approx(12.0) and abs(cropped.cy - H / 2) == pytest.approx(8.0)
    res = align_images(crops, PREVIEW, intrinsics=cropped, names=[p.name for p in paths])
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt.cam_from_world_by_name())
    full = align_images(paths, PREVIEW, intrinsics=cam)
    m_full = compare_poses(full.sparse_model.cam_from_world_by_name(), gt.cam_from_world_by_name())
    assert m.n_registered == len(paths)
    assert m.median_rotation_deg < max(2.0 * m_full.median_rotation_deg, 0.05), (m.summary(), m_full.summary())
