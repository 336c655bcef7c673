"""`mvgeo.align.pair_focal`: the shared focal the pairs agree on (against the rule written out in plain
Python), and the diagnosis when they do not."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from mvgeo.align.pair_focal import consensus_focal, why_no_focal
from mvgeo.twoview import TwoViewConfig

CFG = TwoViewConfig()


def _rel(success: bool, h_ratio: float | None, focal_px: float | None = None):
    return SimpleNamespace(success=success, homography_ratio=h_ratio, focal_well_determined=focal_px is not None,
                           focal_px=focal_px)


def test_focal_diagnosis_counts_each_cause_once():
    rels = [_rel(False, 0.99), _rel(False, CFG.max_homography_ratio),  # homography: planar / no baseline
            _rel(True, 0.4), _rel(True, None),  # a pose, but the focal too uncertain
            _rel(False, 0.2), None]  # no pose (None: OpenCV's estimator raised)
    why = why_no_focal(rels, CFG)
    assert why.startswith("of the 6 pairs tried")
    assert f"in 2 a homography explains at least {CFG.max_homography_ratio:.0%}" in why
    assert "no baseline" in why
    assert "in 2 the focal is too uncertain" in why
    assert "2 gave no relative pose" in why


def test_focal_diagnosis_names_only_the_causes_that_occur():
    why = why_no_focal([_rel(True, 0.1)], CFG)
    assert why == "of the 1 pair tried, in 1 the focal is too uncertain (e.g. an object-centric orbit)"
    assert why_no_focal([], CFG) == "no pair has enough matches to try"


def test_focal_diagnosis_lists_well_determined_focals_that_do_not_agree():
    why = why_no_focal([_rel(True, 0.1, 398.4), _rel(True, 0.2, 153.0), _rel(True, 0.1)], CFG)
    assert "2 well-determined focals (153, 398 px) too few to agree" in why
    assert "in 1 the focal is too uncertain" in why


def _consensus_reference(focals, n_tried, k, tol):
    """The rule written out in plain Python: the focals within `tol` (log) of the median of all agree; they
    decide when there are at least min(k, n_tried) of them and a strict majority."""
    med = sorted(focals)[len(focals) // 2] if len(focals) % 2 else 0.5 * (
        sorted(focals)[len(focals) // 2 - 1] + sorted(focals)[len(focals) // 2])
    agree = sorted(f for f in focals if abs(math.log(f / med)) <= tol)
    if len(agree) < min(k, n_tried) or 2 * len(agree) <= len(focals):
        return None
    m = len(agree)
    return agree[m // 2] if m % 2 else 0.5 * (agree[m // 2 - 1] + agree[m // 2])


@pytest.mark.parametrize("focals, n_tried, expected", [
    # llff_like: ten pairs within 9 % of their median -> their median
    ([398, 401, 403, 406, 410, 414, 419, 429, 438, 447], 10, 412.0),
    ([139.3], 10, None),  # one pair (DTU scan24, truth 925 px): not a consensus
    ([398, 274, 153], 10, None),  # three that disagree
    ([407, 411, 425], 3, 411.0),  # three views: all three pairs agree
    ([500.0], 1, 500.0),  # two views: the only pair decides
    ([400, 410, 420, 150, 160], 10, 410.0),  # three agree, two outliers: a strict majority
    ([400, 410, 150, 160], 10, None),  # two of four: no majority and fewer than three
    ([], 10, None),
])
def test_consensus_focal_cases(focals, n_tried, expected):
    got = consensus_focal(focals, n_tried, 3, 0.15)
    assert got == expected
    if focals:
        assert got == _consensus_reference(focals, n_tried, 3, 0.15)


def test_consensus_focal_matches_the_reference_on_random_sets():
    rng = np.random.default_rng(3)
    for _ in range(300):
        n = int(rng.integers(1, 9))
        focals = list(np.exp(rng.normal(6.0, rng.choice([0.05, 0.5]), n)))
        n_tried = int(rng.integers(n, 11))
        got = consensus_focal(focals, n_tried, 3, 0.15)
        ref = _consensus_reference(focals, n_tried, 3, 0.15)
        assert (got is None and ref is None) or got == pytest.approx(ref, rel=1e-12)
