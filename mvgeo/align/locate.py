"""Locating a cut-off view from the main group's points: multi-view evidence for a view its pairs cannot vouch for.

The verdict refuses views whose every verified pair to the main group is contradicted (`views_cut_off`). On
weak pairs (a dozen matches, narrow field of view) that pair evidence is ambiguous both ways: the rotation a
linear essential matrix draws from the matches can be 10-30 deg off while the solution is right (DTU scan24,
sigma 25/255, noise seed 0: one view refused with its relative rotations within 0.35 deg), and a wrong group
of views 20 deg off can explain its links' matches and out-count the truth in guided epipolar matching
(the bas-relief ambiguity: two views alone cannot tell). Three views can: points triangulated from two main-
group views at the solution's poses pin the third view's pose by PnP, with no use of its own pairs or its
placement in the solution.

`locate_view` does that: guided matching (`mvgeo.align.guided`) on main-group pairs near the view,
triangulation at the solution's poses, descriptor matching of the view's features to those points (Lowe's
ratio against the nearest *other* point: one surface point triangulated from several pairs is not an
ambiguity), RANSAC PnP at the solution's focal. The view is located when PnP keeps at least
`LOCATE_MIN_INLIERS` inliers and its rotation is within `LOCATE_MAX_ROTATION_DEG` of the solution's.
Measured (`benchmarks/bench_real.py` sets): the refused DTU view, 29 inliers, 0.2 deg from the solution;
the four DTU "spread" views 21 deg off, 0 inliers each.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mvgeo.align.checks import PairCheck
from mvgeo.align.guided import fundamental_from_pose, guided_matches
from mvgeo.align.loops import rotation_angle_deg
from mvgeo.align.pairs import Keypoints
from mvgeo.common.deps import cv2
from mvgeo.pnp import sqpnp_ransac

__all__ = ["LOCATE_MAX_ROTATION_DEG", "LOCATE_MIN_INLIERS", "Located", "locate_cut_off", "locate_view",
           "main_group_points"]

#: PnP inliers a located view needs (pycolmap's two-view minimum, 15; random 2D-3D pairs reach it with
#: negligible probability at `REPROJ_PX` in images of a few hundred pixels).
LOCATE_MIN_INLIERS = 15
#: PnP rotation within this of the solution's (measured 0.2 deg at 29 inliers; under the 5 deg a returned
#: view may be off).
LOCATE_MAX_ROTATION_DEG = 3.0
#: guided matching band for the main group's points (`AlignConfig.consistency_px`'s default).
BAND_PX = 2.0
#: PnP RANSAC reprojection threshold and the triangulated points' reprojection limit (pixels).
REPROJ_PX = 4.0
RATIO = 0.8
#: RANSAC iterations of the PnP: with samples of 4, 99.9 % confidence of an all-inlier sample at an inlier
#: fraction of 0.28 (the located DTU view: 80 of about 200 matches, 0.4).
PNP_ITERATIONS = 1000
#: explained pairs triangulated per view (those with the most verified matches among the ones that include a
#: partner of the view): the DTU view located with 71 inliers drew on 8.
MAX_PAIRS = 6
#: descriptor neighbours searched for the ratio test's second point.
TOP_K = 16
#: two triangulated points closer than this fraction of the points' RMS spread are one surface point.
SAME_POINT_FRACTION = 0.03


@dataclass(frozen=True)
class Located:
    """A PnP of one view on the main group's points. n_inliers: PnP inliers (0: no pose); rotation_deg: its
    rotation's angle from the solution's (nan without a pose); n_points: main-group points it matched
    against; cam_from_world: (3, 4) the PnP pose in the solution's world frame, or None."""

    view: int
    n_inliers: int
    rotation_deg: float
    n_points: int
    cam_from_world: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def ok(self) -> bool:
        """The points locate the view where the solution put it."""
        return self.n_inliers >= LOCATE_MIN_INLIERS and self.rotation_deg <= LOCATE_MAX_ROTATION_DEG

    @property
    def placed_elsewhere(self) -> bool:
        """The points locate the view confidently, away from the solution's pose
        (`mvgeo.align.solve.relocate` re-poses it)."""
        return (self.n_inliers >= LOCATE_MIN_INLIERS and self.rotation_deg > LOCATE_MAX_ROTATION_DEG
                and self.cam_from_world is not None)


def _K(f: float, W: int, H: int) -> np.ndarray:
    return np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])


def main_group_points(cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int],
                      features: Sequence[Keypoints], pairs: Sequence[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Points triangulated from guided matches of `pairs` at the solution's poses, with their descriptors.

    Args:
        cam_from_world: (N, 3, 4) solution poses; focal_px: (N,) focals (pixels of `features`).
        size_wh: (W, H) of the images the features live in (principal point at the centre).
        features: per view, `uv_px` (K, 2) and `root()` (K, D) (`mvgeo.align.features.ImageFeatures`).
        pairs: (a, b) view pairs to triangulate from.

    Returns:
        (P, 3) world points in front of both views and within `REPROJ_PX` of both observations, and (P, D)
        the first view's descriptors of them.
    """
    W, H = size_wh
    pts, descs = [np.zeros((0, 3))], [np.zeros((0, 128), np.float32)]
    for a, b in pairs:
        Ka, Kb = _K(focal_px[a], W, H), _K(focal_px[b], W, H)
        Ta, Tb = cam_from_world[a], cam_from_world[b]
        R = Tb[:, :3] @ Ta[:, :3].T
        t = Tb[:, 3] - R @ Ta[:, 3]
        fa, fb = features[a], features[b]
        m = guided_matches(fa.uv_px, fa.root(), fb.uv_px, fb.root(), fundamental_from_pose(R, t, Ka, Kb),
                           band_px=BAND_PX, ratio=RATIO)
        if len(m) < 2:
            continue
        ua, ub = fa.uv_px[m[:, 0]], fb.uv_px[m[:, 1]]
        Xh = cv2.triangulatePoints(Ka @ Ta, Kb @ Tb, ua.T.astype(np.float64), ub.T.astype(np.float64))
        with np.errstate(divide="ignore", invalid="ignore"):
            X = (Xh[:3] / Xh[3]).T
        ok = np.all(np.isfinite(X), axis=1)
        for T, K, uv in ((Ta, Ka, ua), (Tb, Kb, ub)):
            xc = X @ T[:, :3].T + T[:, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                proj = (xc @ K.T)[:, :2] / xc[:, 2:3]
                ok &= (xc[:, 2] > 0) & (np.linalg.norm(proj - uv, axis=1) < REPROJ_PX)
        pts.append(X[ok])
        descs.append(fa.root()[m[ok, 0]].astype(np.float32))
    return np.concatenate(pts), np.concatenate(descs)


def locate_view(view: int, cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int],
                features: Sequence[Keypoints], points: np.ndarray, point_desc: np.ndarray) -> Located:
    """PnP of `view` on `points` (`main_group_points`), compared with its solution pose.

    Args:
        view: the view to locate; cam_from_world, focal_px, size_wh, features: as `main_group_points`.
        points: (P, 3) world points; point_desc: (P, D) their unit descriptors.
    """
    fv = features[view]
    P = len(points)
    if P < 2 or len(fv.uv_px) == 0:
        return Located(view, 0, float("nan"), P)
    spread = float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))
    k = min(TOP_K, P)
    best = np.empty(len(fv.uv_px), np.int64)
    keep = np.zeros(len(fv.uv_px), bool)
    desc_t = np.ascontiguousarray(point_desc.T)
    for lo in range(0, len(fv.uv_px), 512):
        d2 = np.maximum(2.0 - 2.0 * (fv.root()[lo:lo + 512] @ desc_t), 0.0)
        near = np.argpartition(d2, k - 1, axis=1)[:, :k]
        dn = np.take_along_axis(d2, near, axis=1)
        order = np.argsort(dn, axis=1)
        near, dn = np.take_along_axis(near, order, axis=1), np.take_along_axis(dn, order, axis=1)
        # The nearest *other* surface point among the k nearest descriptors (none: unambiguous).
        other = np.linalg.norm(points[near] - points[near[:, :1]], axis=2) >= SAME_POINT_FRACTION * spread
        second = np.where(other, dn, np.inf).min(axis=1)
        best[lo:lo + 512] = near[:, 0]
        keep[lo:lo + 512] = np.sqrt(dn[:, 0]) < RATIO * np.sqrt(second)
    if keep.sum() < 6:
        return Located(view, 0, float("nan"), P)
    W, H = size_wh
    K_cv = _K(focal_px[view], W, H)
    K_cv[:2, 2] -= 0.5  # OpenCV's pixel centres are at integers, ours at +0.5
    ok, rvec, tvec, inliers = sqpnp_ransac(points[best[keep]].astype(np.float64),
                                           (fv.uv_px[keep] - 0.5).astype(np.float64), K_cv,
                                           reprojection_px=REPROJ_PX, iterations=PNP_ITERATIONS, confidence=0.999)
    if not ok or inliers is None:
        return Located(view, 0, float("nan"), P)
    R = cv2.Rodrigues(rvec)[0]
    return Located(view, len(inliers), rotation_angle_deg(R @ cam_from_world[view][:, :3].T), P,
                   np.concatenate([R, np.asarray(tvec, np.float64).reshape(3, 1)], axis=1))


def locate_cut_off(cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int],
                   features: Sequence[Keypoints], checks: Sequence[PairCheck], bad: Sequence[PairCheck],
                   cut_off: Sequence[int]) -> list[Located]:
    """`locate_view` for every view in `cut_off` (`mvgeo.align.checks.views_cut_off`), on the points of the
    explained pairs (`checks` less `bad`) among the other views that include one of the view's checked
    partners (the part of the scene the view shares with the main group): the `MAX_PAIRS` of them with the
    most verified matches, each triangulated once for all the views."""
    cut = set(cut_off)
    bad_keys = {(c.i, c.j) for c in bad}
    good = [(c.i, c.j) for c in sorted(checks, key=lambda c: -c.n_matches)
            if (c.i, c.j) not in bad_keys and c.i not in cut and c.j not in cut]
    chosen = {}
    for v in cut_off:
        partners = {c.j if c.i == v else c.i for c in checks if v in (c.i, c.j)} - cut
        chosen[v] = [(a, b) for a, b in good if a in partners or b in partners][:MAX_PAIRS]
    points = {ab: main_group_points(cam_from_world, focal_px, size_wh, features, [ab])
              for ab in dict.fromkeys(ab for pairs in chosen.values() for ab in pairs)}
    out = []
    for v in cut_off:
        pts = [points[ab] for ab in chosen[v]]
        X = np.concatenate([p for p, _ in pts]) if pts else np.zeros((0, 3))
        D = np.concatenate([d for _, d in pts]) if pts else np.zeros((0, 128), np.float32)
        out.append(locate_view(v, cam_from_world, focal_px, size_wh, features, X, D))
    return out
