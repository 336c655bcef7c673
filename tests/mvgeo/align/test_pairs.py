"""`mvgeo.align.pairs`: `PairPrediction` checks its shapes; `PairSet.without_pairs` and `PairSet.restricted`
against a slow rebuild by hand."""

import numpy as np
import pytest

from mvgeo.align.pairs import PairFailure, PairGeometry, PairPrediction, PairSet, focal_from_pointmap
from mvgeo.common.errors import ShapeError

from .synthetic import make_pairs, make_views

FOCAL = 30.0


def _pair_set(rng, n=5):
    poses, depths = make_views(n)
    preds = make_pairs(poses, depths, FOCAL, rng, pairs=[(0, 1), (1, 2), (2, 3), (3, 4), (0, 2)])
    geos = [PairGeometry(i, j, rng.random((k + 3, 4)), np.c_[np.eye(3), [1.0, 0.0, 0.0]])
            for k, (i, j) in enumerate([(0, 1), (1, 2), (2, 3), (3, 4), (0, 2), (1, 3), (0, 4)])]
    fails = [PairFailure(1, 4, "only 3 SIFT matches (need 20)"), PairFailure(2, 4, "relative pose: degenerate")]
    return PairSet(preds, fails, geos, focal_determined=True, focal_px=250.0, sensitive_features=True)


def test_without_pairs_drops_them_from_predictions_and_geometries(rng):
    ps = _pair_set(rng)
    gone = {(0, 2), (3, 4), (2, 4)}  # (2, 4) is a failure: failures are kept as they are
    out = ps.without_pairs(gone)
    assert [(p.i, p.j) for p in out.predictions] == [(0, 1), (1, 2), (2, 3)]
    assert [(g.i, g.j) for g in out.geometries] == [(0, 1), (1, 2), (2, 3), (1, 3), (0, 4)]
    assert out.failures == ps.failures
    assert (out.focal_determined, out.focal_px, out.sensitive_features) == (True, 250.0, True)
    for g in out.geometries:  # the kept entries are the same objects
        assert any(g is h for h in ps.geometries)
    assert len(ps.predictions) == 5 and len(ps.geometries) == 7  # the original is unchanged
    assert ps.without_pairs(set()) == ps


def test_restricted_renumbers_the_kept_views_in_the_given_order(rng):
    ps = _pair_set(rng)
    keep = [4, 0, 2, 1]  # view 3 left out; new index = position in `keep`
    out = ps.restricted(keep)
    new = {v: k for k, v in enumerate(keep)}
    # The slow way: every entry whose both views are kept, renumbered, in the original order.
    want_preds = [(new[p.i], new[p.j]) for p in ps.predictions if p.i in new and p.j in new]
    assert [(p.i, p.j) for p in out.predictions] == want_preds == [(1, 3), (3, 2), (1, 2)]
    assert [(g.i, g.j) for g in out.geometries] == [(new[g.i], new[g.j]) for g in ps.geometries
                                                     if g.i in new and g.j in new]
    assert [(f.i, f.j, f.reason) for f in out.failures] == [(3, 0, "only 3 SIFT matches (need 20)"),
                                                            (2, 0, "relative pose: degenerate")]
    by_pair = {(p.i, p.j): p for p in ps.predictions}
    for p in out.predictions:  # the data move with the pair
        src = by_pair[(keep[p.i], keep[p.j])]
        assert p.pts_i is src.pts_i and p.conf_j is src.conf_j
    geo = {(g.i, g.j): g for g in ps.geometries}
    for g in out.geometries:
        np.testing.assert_array_equal(g.matches_px, geo[(keep[g.i], keep[g.j])].matches_px)
    assert out.matches == [(g.i, g.j, g.matches_px) for g in out.geometries]
    assert ps.restricted(range(5)) == ps


def test_pair_prediction_checks_its_shapes(rng):
    pts, conf = np.zeros((4, 5, 3), np.float32), np.ones((4, 5), np.float32)
    with pytest.raises(ShapeError, match="conf_j"):
        PairPrediction(0, 1, pts, pts, conf, conf[:3], 10.0)
    with pytest.raises(ShapeError, match="two different views"):
        PairPrediction(2, 2, pts, pts, conf, conf, 10.0)
    with pytest.raises(ShapeError):
        PairGeometry(0, 1, np.zeros((5, 3)))
    with pytest.raises(ShapeError):
        PairGeometry(0, 1, np.zeros((5, 4)), np.eye(3))
    p = PairPrediction(0, 1, pts, pts, conf * 2, conf * 3, 10.0)
    assert p.score == pytest.approx(6.0)


def test_focal_from_pointmap_is_exact_on_an_exact_pointmap(rng):
    poses, depths = make_views(2)
    pred = make_pairs(poses, depths, FOCAL, rng, pairs=[(0, 1)])[0]
    assert focal_from_pointmap(pred.pts_i.astype(np.float64)) == pytest.approx(FOCAL, rel=1e-5)
    assert focal_from_pointmap(pred.pts_i.astype(np.float64), pred.conf_i) == pytest.approx(FOCAL, rel=1e-5)
    assert np.isnan(focal_from_pointmap(-np.abs(pred.pts_i)))  # nothing in front of the camera
