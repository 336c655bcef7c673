"""`mvgeo.align.classical_pairs`: the `PairSet` the classical model returns, features and matches computed once
and reused by `refocus`, the dense-pair selection, and the diagnosis of an undetermined focal."""

import dataclasses

import numpy as np
import pytest

import mvgeo.align.classical_pairs as cp
from mvgeo.align.api import PREVIEW
from mvgeo.align.classical_pairs import ClassicalPointmapModel, select_dense_pairs
from mvgeo.align.graph import components
from mvgeo.align.loops import rotation_angle_deg
from mvgeo.align.pairs import PairSet, PointmapModel, RefocusableModel
from mvgeo.common.imageio import list_images, read_image
from mvgeo.sparse_model import read_sparse_model

PAIRS = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


@pytest.fixture(scope="module")
def views4(llff6):
    paths = list_images(llff6 / "images")[:4]
    return [p.name for p in paths], [read_image(p) for p in paths]


@pytest.fixture(scope="module")
def pairset4(views4) -> PairSet:
    return ClassicalPointmapModel(PREVIEW.pairwise, seed=0).predict_pairs(views4[1], PAIRS)


def test_classical_model_is_a_refocusable_pointmap_model():
    model = ClassicalPointmapModel()
    assert isinstance(model, PointmapModel) and isinstance(model, RefocusableModel)
    assert model.pointmap_size_px == cp.ClassicalPairConfig().pointmap_size_px


def test_pair_set_holds_every_verified_pair_with_its_geometry(pairset4, views4, llff6):
    ps = pairset4
    geo = {(g.i, g.j): g for g in ps.geometries}
    failed = {(f.i, f.j) for f in ps.failures}
    assert set(geo) | failed == set(PAIRS)  # every pair is verified or has a reason
    assert all(f.reason for f in ps.failures)
    assert len(ps.predictions) >= 3 and len(components(4, [(p.i, p.j) for p in ps.predictions])) == 1
    H, W = views4[1][0].shape[:2]
    for p in ps.predictions:  # the dense pairs are verified pairs; their matches are the geometry's
        np.testing.assert_array_equal(p.matches_px, geo[(p.i, p.j)].matches_px)
        assert max(p.pts_i.shape[:2]) == PREVIEW.pairwise.pointmap_size_px and np.all(p.conf_i >= 1)
        assert p.focal_i_px == pytest.approx(ps.focal_px * p.pts_i.shape[1] / W)
    assert [(i, j) for i, j, _ in ps.matches] == list(geo)
    # The relative poses: unit translation, and close to the truth at the true focal (noisy 256x192 views;
    # measured 0.19-1.36 deg off with PREVIEW, seed 0). The pair stage's own focal here is the prior: one of
    # the six pairs has a well-determined focal, too few to agree (`consensus_focal`).
    gt = read_sparse_model(llff6 / "sparse" / "0")
    T = [np.asarray(gt.image(n).cam_from_world)[:3] for n in views4[0]]
    f_true = gt.camera_of(views4[0][0]).fx
    at_truth = ClassicalPointmapModel(PREVIEW.pairwise, seed=0).refocus(views4[1], PAIRS, f_true)
    for (i, j), g in {(g.i, g.j): g for g in at_truth.geometries}.items():
        assert len(g.matches_px) >= 15
        assert np.all((g.matches_px >= 0) & (g.matches_px <= [W, H, W, H]))
        R, t = g.cam_j_from_cam_i[:, :3], g.cam_j_from_cam_i[:, 3]
        assert np.linalg.norm(t) == pytest.approx(1.0)
        R_true = T[j][:, :3] @ T[i][:, :3].T
        assert rotation_angle_deg(R @ R_true.T) < 3.0, (i, j)


def test_match_is_computed_once_and_refocus_reuses_it(views4, monkeypatch):
    """Features and matches: once for the same images and pairs; `refocus` recomputes the geometry at another
    focal from them; other pairs or other images are matched anew."""
    real, calls = cp.detect_and_match, []

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(cp, "detect_and_match", counting)
    images = views4[1][:3]
    pairs = [(0, 1), (0, 2), (1, 2)]
    # No pair focal (focal_pairs=0): the prior 1.2 * max(W, H).
    model = ClassicalPointmapModel(dataclasses.replace(PREVIEW.pairwise, focal_pairs=0), seed=0)
    first = model.predict_pairs(images, pairs)
    assert len(calls) == 1
    assert first.focal_px == pytest.approx(1.2 * 256) and not first.focal_determined
    assert first.focal_undetermined_why == "no pair has enough matches to try"
    matched = model.match(images, pairs)
    again = model.predict_pairs([im.copy() for im in images], pairs)  # equal images: the same key
    assert len(calls) == 1 and model.match(images, pairs) is matched
    assert [(p.i, p.j) for p in again.predictions] == [(p.i, p.j) for p in first.predictions]
    for a, b in zip(again.predictions, first.predictions, strict=True):
        np.testing.assert_array_equal(a.pts_j, b.pts_j)
    refocused = model.refocus(images, pairs, 200.0)
    assert len(calls) == 1  # the same features and matches
    assert refocused.focal_px == 200.0 and len(refocused.predictions) >= 2
    Wp = refocused.predictions[0].pts_i.shape[1]
    np.testing.assert_allclose([p.focal_i_px for p in refocused.predictions], 200.0 * Wp / 256)
    # Every refocused pair's inliers are among the pair's putative matches.
    for g in refocused.geometries:
        u1, u2 = matched.pixels(g.i, g.j)
        putative = {tuple(r) for r in np.concatenate([u1, u2], axis=1)}
        assert {tuple(r) for r in g.matches_px} <= putative
    model.predict_pairs(images, pairs[:2])  # other pairs: matched anew
    assert len(calls) == 2
    model.predict_pairs(images[::-1], pairs)  # other images (order): matched anew
    assert len(calls) == 3


def _assert_same_pairs(a: PairSet, b: PairSet) -> None:
    assert [(p.i, p.j) for p in a.predictions] == [(p.i, p.j) for p in b.predictions]
    for x, y in zip(a.predictions, b.predictions, strict=True):
        for field in ("pts_i", "pts_j", "conf_i", "conf_j", "matches_px"):
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
    assert [(g.i, g.j) for g in a.geometries] == [(g.i, g.j) for g in b.geometries]
    for x, y in zip(a.geometries, b.geometries, strict=True):
        np.testing.assert_array_equal(x.matches_px, y.matches_px)
        np.testing.assert_array_equal(x.cam_j_from_cam_i, y.cam_j_from_cam_i)


def test_refocus_reuses_the_flows_of_unchanged_pairs_with_the_same_result(views4, monkeypatch):
    """A refocused `relate` takes the dense flows of the pairs whose inliers (and images) did not change from
    the previous `relate`; its pairs are exactly those of a model that computes every flow anew."""
    real, calls = cp.pair_flows, []

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(cp, "pair_flows", counting)
    images = views4[1]
    cfg = dataclasses.replace(PREVIEW.pairwise, focal_pairs=0)
    model = ClassicalPointmapModel(cfg, seed=0)
    first = model.predict_pairs(images, PAIRS)
    n_first = len(calls)
    assert n_first == len(first.predictions)
    same = model.refocus(images, PAIRS, first.focal_px)  # the same focal: the same inliers, every flow reused
    assert len(calls) == n_first
    _assert_same_pairs(same, first)
    for f in (first.focal_px * 1.05, 200.0):  # other focals: only changed pairs recompute their flows
        before = len(calls)
        cached = model.refocus(images, PAIRS, f)
        assert len(calls) - before <= len(cached.predictions)
        fresh_model = ClassicalPointmapModel(cfg, seed=0)
        fresh_model.match(images, PAIRS)
        fresh = fresh_model.refocus(images, PAIRS, f)
        _assert_same_pairs(cached, fresh)
    # Other images: nothing is reused (the key holds the pointmap-grid images).
    before = len(calls)
    darker = [np.clip(im * 0.9, 0.0, 1.0).astype(im.dtype) for im in images]
    out = model.predict_pairs(darker, PAIRS)
    assert len(calls) - before == len(out.predictions)


def test_dense_pair_selection_is_connected_and_top_k(rng):
    n = 10
    inliers = {(i, j): int(rng.integers(20, 500)) for i in range(n) for j in range(i + 1, n) if rng.random() < 0.6}
    inliers.update({(i, i + 1): 25 for i in range(n - 1)})  # a weak chain keeps the full graph connected
    for k in (1, 2, 4):
        sel = select_dense_pairs(n, inliers, k)
        assert len(components(n, sel)) == 1
        for v in range(n):
            mine = sorted((p for p in inliers if v in p), key=lambda p: -inliers[p])[:k]
            assert set(mine) <= set(sel)
    assert sorted(select_dense_pairs(n, inliers, 0)) == sorted(inliers)
