"""`ColmapConfig.known_pinhole`: pycolmap's mappers with a known, fixed PINHOLE camera (the reference for
`mvgeo align --intrinsics`): the model keeps the camera exactly and registers the views."""

import dataclasses

import numpy as np
import pytest

from mvgeo.align.colmap_sfm import ColmapConfig, run_colmap
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_the_known_camera_is_kept_fixed(llff6, mapper):
    gt = read_sparse_model(llff6 / "sparse" / "0")
    cam = gt.camera_of(gt.names[0])
    known = (cam.fx * 1.01, cam.fy * 1.01, cam.cx, cam.cy)  # off by 1 %: an estimated focal would move
    res = run_colmap(llff6 / "images", ColmapConfig(mapper=mapper, known_pinhole=known))
    (model_cam,) = res.sparse_model.cameras.values()
    assert model_cam.model == "PINHOLE"
    np.testing.assert_array_equal(model_cam.params, np.array(known))
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt.cam_from_world_by_name())
    assert m.n_registered >= 4 and m.median_rotation_deg < 1.0


def test_without_a_known_camera_the_focal_is_estimated(llff6):
    gt = read_sparse_model(llff6 / "sparse" / "0")
    cam = gt.camera_of(gt.names[0])
    res = run_colmap(llff6 / "images", dataclasses.replace(ColmapConfig(), mapper="incremental"))
    (model_cam,) = res.sparse_model.cameras.values()
    assert model_cam.model == "SIMPLE_RADIAL" and model_cam.fx != cam.fx
