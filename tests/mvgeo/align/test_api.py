"""`align_images` end to end (the Python API): its result, its report, the files it writes, and the native-thread
limit it runs under."""

import json

import numpy as np

from mvgeo.align import write_align_result
from mvgeo.align.stats import AlignStats
from mvgeo.common.deps import cv2
from mvgeo.common.imageio import list_images
from mvgeo.common.threads import blas_thread_counts, native_threads
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


def test_native_threads_limits_and_restores():
    before, cv_before = blas_thread_counts(), cv2.getNumThreads()
    assert before  # numpy's OpenBLAS is loaded in this process (Linux wheels)
    with native_threads(1):
        assert blas_thread_counts() == [1] * len(before)
        assert cv2.getNumThreads() == 1
    assert blas_thread_counts() == before and cv2.getNumThreads() == cv_before


def test_the_alignment_pools_run_the_callers_threads(tmp_path, monkeypatch):
    """A one-CPU Ray task runs with one torch thread (`eval.distributed`): its alignment's pools over pairs,
    views and files ran one thread per core of the node (2 at once per task on 2 cores, 16 on a 16-core
    node), where the task was given one."""
    import mvgeo.align.inputs as inputs
    from mvgeo.align.classical_pairs import ClassicalPairConfig, ClassicalPointmapModel
    from mvgeo.common.imageio import write_image
    from mvgeo.common.threads import pool_threads, torch_threads

    sizes = []

    class Recorder(inputs.ThreadPoolExecutor):
        def __init__(self, max_workers=None, **kw):
            sizes.append(max_workers)
            super().__init__(max_workers, **kw)

    monkeypatch.setattr(inputs, "ThreadPoolExecutor", Recorder)
    files = [tmp_path / f"{k}.png" for k in range(3)]
    for f in files:
        write_image(f, np.full((8, 8, 3), 0.5, np.float32))
    with torch_threads(1):
        assert pool_threads() == 1 and pool_threads(4) == 4 and pool_threads(0, 3) == 1
        with ClassicalPointmapModel()._pool() as pool:
            assert pool._max_workers == 1
        inputs._read(files, None)
    assert sizes == [1]
    with torch_threads(3):
        assert pool_threads() == 3 and pool_threads(None, 2) == 2
        with ClassicalPointmapModel(ClassicalPairConfig(workers=2))._pool() as pool:
            assert pool._max_workers == 2


def test_result_and_typed_report(llff6, llff6_preview):
    res = llff6_preview
    names = [p.name for p in list_images(llff6 / "images")]
    assert [im.name for im in res.sparse_model.images] == names  # input order, names as given
    s = res.stats
    assert isinstance(s, AlignStats)
    assert (s.n_images, s.n_registered, s.unregistered) == (6, 6, [])
    assert s.input_size_wh == [256, 192] and s.align_size_wh == [256, 192]
    assert max(s.pointmap_size_wh) == 96  # PREVIEW's pointmaps
    assert s.n_pairs == 15 and 0 < s.n_pairs_ok <= s.n_pairs_verified <= 15
    assert s.n_points == len(res.points_xyz) == len(res.points_rgb) == len(res.points_conf) > 100
    assert res.points_rgb.dtype == np.uint8 and np.all(res.points_conf > 2.0)  # above min_conf
    assert sorted(s.focal_px) == sorted(names) and len(set(s.focal_px.values())) == 1  # one shared camera
    assert s.final_loss <= s.init_loss
    ba = s.bundle_adjustment
    assert ba is not None and ba.reproj_rms_after_px < ba.reproj_rms_before_px and ba.n_points > 100
    assert len(ba.centre_std_ratio) == 6 and max(ba.centre_std_ratio) <= 1.0  # every position determined
    assert ba.views == names  # the views the per-view lists follow
    assert s.pairs_inconsistent == [] and s.pair_consistency_min >= 0.5
    for stage in ("load", "pairwise", "global_align", "bundle_adjust", "dense_stereo", "total"):
        assert stage in s.timings_s, stage
    assert s.config["max_size_px"] == 320 and s.config["initial_poses"] == "auto"
    m = compare_poses(res.sparse_model.cam_from_world_by_name(),
                      read_sparse_model(llff6 / "sparse" / "0").cam_from_world_by_name())
    # Measured 0.35 deg with PREVIEW (noisy 256x192 views); 1 deg leaves room for other machines' SIFT.
    assert m.registered_fraction == 1.0 and m.median_rotation_deg < 1.0


def test_written_result_reads_back(llff6_preview, tmp_path):
    out = write_align_result(tmp_path / "out", llff6_preview)
    raw = json.loads((out / "align.json").read_text())
    assert raw["n_points"] == llff6_preview.stats.n_points and "annotations" not in raw
    assert AlignStats.read(out / "align.json") == llff6_preview.stats
    model = read_sparse_model(out / "sparse" / "0")
    assert model.names == llff6_preview.sparse_model.names
    for a, b in zip(model.images, llff6_preview.sparse_model.images, strict=True):
        np.testing.assert_allclose(np.asarray(a.cam_from_world)[:3], np.asarray(b.cam_from_world)[:3], atol=1e-9)


def test_the_cloud_is_made_of_the_cloud_images(llff6, llff6_preview):
    """`cloud_images`: the poses come from `images` alone, the dense cloud (stereo and colours) from the cloud
    images: with flat grey cloud images (one level per view) every point's colour is its view's grey."""
    import dataclasses

    import pytest

    from mvgeo.align import PREVIEW, align_images
    from mvgeo.common.errors import InputError

    files = list_images(llff6 / "images")
    greys = [(40 + 25 * k) / 255 for k in range(len(files))]
    flat = [np.full((192, 256, 3), g, np.float32) for g in greys]
    res = align_images(files, dataclasses.replace(PREVIEW, seed=0), cloud_images=flat)
    poses = lambda r: np.stack(list(r.sparse_model.cam_from_world_by_name().values()))  # noqa: E731
    np.testing.assert_array_equal(poses(res), poses(llff6_preview))
    levels = {int(np.rint(g * 255)) for g in greys}
    assert len(res.points_rgb) > 100 and set(np.unique(res.points_rgb)) <= levels
    assert len(set(np.unique(res.points_rgb)) & levels) > 1  # points of several views
    with pytest.raises(InputError, match="5 cloud images for 6 images"):
        align_images(files, PREVIEW, cloud_images=flat[:5])
    with pytest.raises(InputError, match="the cloud images are 128x96"):
        align_images(files, PREVIEW, cloud_images=[f[:96, :128] for f in flat])
    from mvgeo.camera import Camera

    calibration = Camera.pinhole(200.0, 200.0, 128.0, 96.0, 256, 192)  # fits the images: the cloud's are named
    with pytest.raises(InputError, match="the cloud images are 128x96, the images 256x192"):
        align_images(files, PREVIEW, intrinsics=calibration, cloud_images=[f[:96, :128] for f in flat])
    mixed = [f[:96, :128] if k == 2 else f for k, f in enumerate(flat)]  # a problem of the set is named as theirs
    for calib in (None, calibration):
        with pytest.raises(InputError, match="the cloud images: images have different sizes"):
            align_images(files, PREVIEW, intrinsics=calib, cloud_images=mixed)


def test_an_estimated_focal_is_square_at_the_input_size_whatever_the_grid_rounds_to():
    """The focal is estimated for square pixels at the alignment size; a pointmap grid whose aspect ratio rounds
    away from the image's (250x165 at a 96x63 grid) does not make the written fy differ from fx (it was 0.57 %
    longer: fy scaled by the grid's height)."""
    from types import SimpleNamespace

    from mvgeo.align.api import _sparse_model
    from mvgeo.align.cloud import DenseCloud

    for (W0, H0), (Wa, Ha), (Wp, Hp) in [((250, 165), (250, 165), (96, 63)), ((6000, 4000), (640, 427), (128, 85))]:
        f_grid = 80.0
        inputs = SimpleNamespace(input_wh=(W0, H0), align_wh=(Wa, Ha), intrinsics=None, K_align=None,
                                 names=["a.png", "b.png"])
        pose = np.hstack([np.eye(3), np.zeros((3, 1))])
        c = SimpleNamespace(inputs=inputs, graph=SimpleNamespace(grid_to_align=Wa / Wp),
                            result=SimpleNamespace(depth=[np.ones((Hp, Wp))] * 2, focal_px=np.full(2, f_grid),
                                                   cam_from_world=np.stack([pose, pose])))
        cloud = DenseCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.float32), None)
        cam = _sparse_model(c, cloud).cameras[1]
        f_align = f_grid * Wa / Wp  # the bundle adjustment's and the dense stereo's focal
        np.testing.assert_allclose([cam.fx, cam.fy], [f_align * W0 / Wa, f_align * H0 / Ha], rtol=1e-12)
        assert (cam.cx, cam.cy) == (W0 / 2.0, H0 / 2.0)
