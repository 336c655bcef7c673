"""The undetermined-focal failure says why the pairs did not determine the focal."""

from types import SimpleNamespace

from mvgeo.align.classical_pairs import _why_no_focal
from mvgeo.twoview import TwoViewConfig

CFG = TwoViewConfig()


def _rel(success: bool, h_ratio: float | None):
    return SimpleNamespace(success=success, homography_ratio=h_ratio, focal_well_determined=False)


def test_counts_each_cause_once():
    rels = [_rel(False, 0.99), _rel(False, CFG.max_homography_ratio),  # homography: planar / no baseline
            _rel(True, 0.4), _rel(True, None),  # a pose, but the focal too uncertain
            _rel(False, 0.2), None]  # no pose (None: OpenCV's estimator raised)
    why = _why_no_focal(rels, CFG)
    assert why.startswith("of the 6 pairs tried")
    assert f"in 2 a homography explains at least {CFG.max_homography_ratio:.0%}" in why
    assert "no baseline" in why
    assert "in 2 the focal is too uncertain" in why
    assert "2 gave no relative pose" in why


def test_only_the_causes_that_occur_are_named():
    why = _why_no_focal([_rel(True, 0.1)], CFG)
    assert why == "of the 1 pair tried, in 1 the focal is too uncertain (e.g. an object-centric orbit)"
    assert _why_no_focal([], CFG) == "no pair has enough matches to try"
