"""The alignment's check that every camera position is determined by the tracks (`max_centre_std_ratio`)."""

import numpy as np
import pytest

from mvgeo.align.api import AlignConfig, _centre_std_ratio, _loose_views
from mvgeo.align.bundle import BundleResult


def _result(centres, centre_std):
    R = np.repeat(np.eye(3)[None], len(centres), axis=0)
    t = -np.asarray(centres, float)  # cam_from_world with R = I: t = -C
    cams = np.concatenate([R, t[:, :, None]], axis=2)
    return BundleResult(cams, np.full(len(centres), 500.0), 10, 20, 1.0, 0.5, 1.0, 0.5,
                        centre_std=np.asarray(centre_std, float))


def test_ratio_is_std_over_median_nearest_neighbour_distance():
    # Centres on a line 1, 1, 2 apart: nearest-neighbour distances 1, 1, 1, 2 -> median 1.
    ba = _result([[0, 0, 0], [1, 0, 0], [2, 0, 0], [4, 0, 0]], [0.01, 0.02, 0.5, 3.0])
    assert _centre_std_ratio(ba) == pytest.approx([0.01, 0.02, 0.5, 3.0])
    assert _loose_views(ba, AlignConfig()) == [3]
    assert _loose_views(ba, AlignConfig(max_centre_std_ratio=0.4)) == [2, 3]
    assert _loose_views(ba, AlignConfig(max_centre_std_ratio=0.0)) == []  # check off


def test_no_estimate_no_verdict():
    ba = _result([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [0.0, 0.0, 0.0])
    ba.centre_std = None  # the scipy solver gives none
    assert _centre_std_ratio(ba) is None
    assert _loose_views(ba, AlignConfig()) == []
    assert _loose_views(None, AlignConfig()) == []
    # Two views: the distance between them is the scale gauge, never judged.
    assert _centre_std_ratio(_result([[0, 0, 0], [1, 0, 0]], [50.0, 50.0])) is None


def test_coincident_centres_count_as_undetermined():
    ba = _result([[0, 0, 0], [0, 0, 0], [0, 0, 0]], [0.0, 0.1, 0.1])
    assert _loose_views(ba, AlignConfig()) == [0, 1, 2]
