"""Focal re-estimation: pairs computed again with the bundle adjustment's focal when it moved far.

Two-view focal estimates are poor for narrow fields of view (12 DTU scan24 views, 925 px at 384 px:
pair estimates scattered from 77 to 7000 px). The pairs' relative poses and dense pointmaps are built
with the shared focal, so a bad one bends the global alignment; the bundle adjustment then moves the
focal most of the way back, and a second pass of the pairs with that focal recovers.
"""

import dataclasses

import numpy as np
import pytest

from mvgeo.align.api import PREVIEW, align_images
from mvgeo.align.classical_pairs import ClassicalPointmapModel
from mvgeo.common.errors import DegenerateGeometryError
from mvgeo.common.imageio import list_images, read_image
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


@pytest.fixture(scope="module")
def llff6(tmp_path_factory):
    from data_synth import render_scene

    return render_scene("llff_like", tmp_path_factory.mktemp("refocus") / "llff", views=6, size_wh=(256, 192))


def _config(prior: float, min_change: float):
    # No pair focal: the pairs use `prior * max(W, H)`, a controlled wrong start.
    return dataclasses.replace(PREVIEW, seed=0, refocus_min_change=min_change,
                               pairwise=dataclasses.replace(PREVIEW.pairwise, focal_pairs=0, focal_prior=prior))


def test_a_focal_far_off_is_re_estimated(llff6):
    gt = read_sparse_model(llff6 / "sparse" / "0")
    f_true = gt.camera_of(gt.names[0]).params[0]  # 208.9 px at 256x192
    files = list_images(llff6 / "images")
    # 0.6 * 256 = 154 px, 26 % under the truth. Measured 2026-11-22: without the second pass the checks
    # refuse the result (11 of 15 pairs inconsistent); with it, 207.1 px (0.9 % off). (Without the second
    # pass but with the initialisation fallback, `init_fallback`, the pairs' own poses pass too: 6/6 at
    # 0.22 deg, 200.9 px, measured 2026-11-25; the fallback is off here to see the second pass alone.)
    with pytest.raises(DegenerateGeometryError, match="inconsistent"):
        align_images(files, dataclasses.replace(_config(0.6, 0.0), init_fallback=False))
    res = align_images(files, _config(0.6, 0.1))
    info = res.stats["focal_reestimation"]
    assert info["refocused"] and info["kept"] == "second pass"
    assert info["pairs_focal_px"] == pytest.approx(153.6)
    f = np.array([c.params[0] for c in res.sparse_model.cameras.values()])
    assert np.all(np.abs(f / f_true - 1.0) < 0.03), f  # 3 %: three times the measured 0.9 %
    # (PREVIEW from the default pair focal: 0.35 deg)
    gt_poses = {n: np.asarray(gt.image(n).cam_from_world)[:3] for n in gt.names}
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt_poses)
    assert m.n_registered == 6 and m.median_rotation_deg < 0.5, m  # measured 0.08 deg


def test_a_focal_close_enough_is_not_re_estimated(llff6):
    """The default pair focal on llff_like: the adjustment moves it by less than 10 %, one pass only."""
    res = align_images(list_images(llff6 / "images"), dataclasses.replace(PREVIEW, seed=0))
    info = res.stats["focal_reestimation"]
    assert info is not None and not info["refocused"]
    assert abs(np.log(info["bundle_focal_px"] / info["pairs_focal_px"])) <= 0.1
    # One shared focal in the bundle adjustment: one camera for all views, as COLMAP's single-camera mode.
    assert len(res.sparse_model.cameras) == 1
    assert {im.camera_id for im in res.sparse_model.images} == {1}


def test_refocused_model_reuses_the_matches(llff6, monkeypatch):
    images = [read_image(p) for p in list_images(llff6 / "images")[:3]]
    model = ClassicalPointmapModel(dataclasses.replace(PREVIEW.pairwise, focal_pairs=0), seed=0)
    with pytest.raises(ValueError, match="predict_pairs"):
        model.refocused(200.0, 3)
    pairs = [(0, 1), (0, 2), (1, 2)]
    model.predict_pairs(images, pairs)
    assert model.focal_px_used == pytest.approx(1.2 * 256)
    with pytest.raises(ValueError, match="predict_pairs"):
        model.refocused(200.0, 4)  # another image count

    def no_sift(*args, **kwargs):
        raise AssertionError("the refocused model must reuse the features and matches")

    again = model.refocused(200.0, 3)
    monkeypatch.setattr(again, "_features_and_matches", no_sift)
    preds, _ = again.predict_pairs(images, pairs)
    assert again.focal_px_used == 200.0 and not again.focal_determined
    assert len(preds) >= 2
    np.testing.assert_allclose(again.K_align[:, 0, 0], 200.0)


def test_the_first_pass_is_kept_when_the_second_fails(llff6, monkeypatch):
    import mvgeo.align.api as api

    real, calls = api._solve, []

    def second_fails(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise DegenerateGeometryError("stand-in failure of the second pass")
        return real(*args, **kwargs)

    monkeypatch.setattr(api, "_solve", second_fails)
    # 2.0 * 256 = 512 px, 2.5x the truth: the first pass still passes its checks (measured: 194 px), and the
    # adjustment's move triggers the second pass.
    res = align_images(list_images(llff6 / "images"), _config(2.0, 0.1))
    info = res.stats["focal_reestimation"]
    assert len(calls) == 2 and info["refocused"]
    assert info["kept"].startswith("first pass (the second failed: stand-in failure")
    assert res.stats["n_registered"] == 6


def test_a_second_start_reuses_the_pair_stage(llff6, monkeypatch):
    images = [read_image(p) for p in list_images(llff6 / "images")[:3]]
    model = ClassicalPointmapModel(PREVIEW.pairwise, seed=0)
    pairs = [(0, 1), (0, 2), (1, 2)]
    preds, fails = model.predict_pairs(images, pairs)
    sparse = model.sparse_matches

    def no_pairs(*args, **kwargs):
        raise AssertionError("the same images and pairs must reuse the pair stage")

    monkeypatch.setattr(model, "_predict_pairs", no_pairs)
    again, fails_again = model.predict_pairs(images, pairs)
    assert [(p.i, p.j) for p in again] == [(p.i, p.j) for p in preds] and len(fails_again) == len(fails)
    for a, b in zip(again, preds, strict=True):
        np.testing.assert_array_equal(a.pts_j, b.pts_j)
    assert model.sparse_matches is sparse
    with pytest.raises(AssertionError, match="reuse the pair stage"):
        model.predict_pairs(images, pairs[:2])  # other pairs: computed anew
