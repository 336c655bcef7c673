"""The one focal length a set of photos shares, read from the pairs' two-view focals.

Each uncalibrated pair (`mvgeo.twoview.estimate_relative_pose_uncalibrated`) gives a focal, and says
whether it is well determined. `consensus_focal` keeps the well-determined ones that agree with their
median and decides only on a majority; when it cannot, `why_no_focal` says why, counting each cause once
(a homography: no baseline; a loose focal: e.g. an object-centric orbit; no pose; too few that agree).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvgeo.twoview import TwoViewConfig

__all__ = ["consensus_focal", "why_no_focal"]


def consensus_focal(focals_px: Sequence[float], n_tried: int, min_agreeing: int, agree_log: float) -> float | None:
    """The shared focal that well-determined pair focals agree on, or None.

    The focals within `agree_log` (|log(f / median)|) of their median agree; with at least
    `min(min_agreeing, n_tried)` of them, and more than half of all, their median is returned.

    Args:
        focals_px: the well-determined pair focals.
        n_tried: how many pairs were tried (so that two or three views can still determine it).
    """
    if not len(focals_px):
        return None
    f = np.asarray(focals_px, np.float64)
    agree = f[np.abs(np.log(f / np.median(f))) <= agree_log]
    if len(agree) < min(min_agreeing, n_tried) or 2 * len(agree) <= len(f):
        return None
    return float(np.median(agree))


def why_no_focal(rels: Sequence, two_view: TwoViewConfig) -> str:
    """Why none of the pairs tried determined the focal: counts of the causes, most specific first.

    `rels` are the pairs' uncalibrated relative poses (None: OpenCV's estimator failed on the pair).
    """
    if not rels:
        return "no pair has enough matches to try"
    planar = sum(r is not None and (r.homography_ratio or 0.0) >= two_view.max_homography_ratio for r in rels)
    failed = sum(r is None or (not r.success and (r.homography_ratio or 0.0) < two_view.max_homography_ratio)
                 for r in rels)
    disagree = sorted(round(float(r.focal_px)) for r in rels if r is not None and r.success
                      and r.focal_well_determined and (r.homography_ratio or 0.0) < two_view.max_homography_ratio)
    loose = len(rels) - planar - failed - len(disagree)
    parts = []
    if planar:
        parts.append(f"in {planar} a homography explains at least {two_view.max_homography_ratio:.0%} of the "
                     "matches (a planar scene, or a camera rotating about its centre: no baseline)")
    if loose:
        parts.append(f"in {loose} the focal is too uncertain (e.g. an object-centric orbit)")
    if failed:
        parts.append(f"{failed} gave no relative pose")
    if disagree:
        parts.append(f"{len(disagree)} well-determined focal{'s' if len(disagree) != 1 else ''} "
                     f"({', '.join(map(str, disagree))} px) too few to agree")
    return f"of the {len(rels)} pair{'s' if len(rels) != 1 else ''} tried, " + "; ".join(parts)
