"""12-view regression against ground truth and pycolmap (slow: ~10 min on the shared 2-core machine)."""

import pytest

from mvgeo.align.api import AlignConfig, align_images
from mvgeo.align.colmap_sfm import run_colmap
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
            compare_poses(col.sparse_model.cam_from_world_by_name(), gt))


def test_ours_registers_all_and_meets_measured_bounds(results):
    ours, _ = results
    assert ours.registered_fraction == 1.0
    # Measured (benchmarks/bench_align.py, docs/bench/align.md): median rotation 0.077 deg, ATE 0.0030
    # (scene units) on llff_like 12 views 504x378 (pycolmap: 0.033 deg, 0.0010). Bounds ~2.6x ours.
    assert ours.median_rotation_deg < 0.2
    assert ours.ate.rmse < 0.008


@pytest.mark.xfail(strict=True, reason="known gap (issue 5): our poses are less accurate than pycolmap's "
                                       "on this scene; see docs/bench/align.md")
def test_ours_at_least_as_accurate_as_colmap(results):
    ours, col = results
    assert col.registered_fraction == 1.0
    assert ours.median_rotation_deg <= col.median_rotation_deg
    assert ours.ate.rmse <= col.ate.rmse
