"""12-view regression against ground truth and pycolmap (slow: ~2 min on the shared 2-core machine)."""

import numpy as np
import pytest

from mvgeo.align.api import AlignConfig, align_images
from mvgeo.align.colmap_sfm import run_colmap
from mvgeo.common.errors import AlignmentRefusedError
from mvgeo.common.imageio import list_images
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def llff12(tmp_path_factory):
    from data_synth import render_scene

    return render_scene("llff_like", tmp_path_factory.mktemp("llff12") / "llff", views=12)


@pytest.fixture(scope="module")
def results(llff12):
    gt = read_sparse_model(llff12 / "sparse" / "0").cam_from_world_by_name()
    ours = align_images(list_images(llff12 / "images"), AlignConfig())
    col = run_colmap(llff12 / "images")
    return (compare_poses(ours.sparse_model.cam_from_world_by_name(), gt),
            compare_poses(col.sparse_model.cam_from_world_by_name(), gt), ours)


def test_ours_registers_all_and_meets_measured_bounds(results):
    ours, _, res = results
    assert ours.registered_fraction == 1.0
    # Measured on llff_like, 12 views 504x378 (docs/bench/align.md and development runs): ours median
    # rotation 0.012-0.019 deg, ATE 0.00047-0.00060; pycolmap incremental 0.033 deg, ATE 0.0010. The
    # bounds are COLMAP's figures: ~1.7x above our worst measured run.
    assert ours.median_rotation_deg < 0.033
    assert ours.ate.rmse < 0.0010
    ba = res.stats.bundle_adjustment
    assert ba.reproj_rms_after_px < ba.reproj_rms_before_px
    assert ba.reproj_rms_after_px < 1.0  # measured 0.56 px at 504x378


def test_ours_at_least_as_accurate_as_colmap(results):
    ours, col, _ = results
    assert col.registered_fraction == 1.0
    assert ours.median_rotation_deg <= col.median_rotation_deg
    assert ours.ate.rmse <= col.ate.rmse


@pytest.mark.parametrize("k", [3, 6])
def test_subsets_register_all_views(llff12, k, tmp_path):
    """Evenly spaced 3- and 6-view subsets: every view registered, bounded error (measured first)."""
    gt = read_sparse_model(llff12 / "sparse" / "0").cam_from_world_by_name()
    names = sorted(gt)
    pick = [names[i] for i in np.linspace(0, 11, k).round().astype(int)]
    res = align_images([llff12 / "images" / n for n in pick], AlignConfig())
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), {n: gt[n] for n in pick})
    assert m.registered_fraction == 1.0
    assert m.median_rotation_deg < SUBSET_ROT_BOUND_DEG[k]


#: Measured on these subsets: ours 0.052 deg (3 views) / 0.019 deg (6 views); pycolmap incremental
#: 0.195 / 0.042 deg (it registers all views here too). Bounds ~2x ours, below COLMAP's figures.
SUBSET_ROT_BOUND_DEG = {3: 0.1, 6: 0.04}


def test_object_ring_is_usable_or_a_specific_failure(tmp_path):
    """Orbit with 30 deg steps and 3-fold symmetric content: pycolmap reconstructs nothing; ours must
    not return a wrong result silently (without the consistency checks it returned one 104 deg off)."""
    from data_synth import render_scene

    d = render_scene("object_ring", tmp_path / "ring", views=12)
    gt = read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()
    try:
        res = align_images(list_images(d / "images"), AlignConfig())
    except AlignmentRefusedError as exc:  # a named reason; on a 2-core Intel Xeon: a view held by one pair
        assert exc.kind in ("pairs_contradicted", "focal_undetermined", "views_unsupported"), exc
        return
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt)
    assert m.registered_fraction == 1.0 and m.median_rotation_deg < 1.0
