"""Consistency checks of a reconstruction against the pairwise evidence it was built from.

A pose-free reconstruction can converge to a wrong but self-consistent
solution (a folded ring, repeated structure matched across the object, an
undetermined focal length): the bundle adjustment then reports a small
reprojection error on the observations it kept while it dropped or bent the
rest. The check here asks every verified pair whether the final poses and
focals explain *its* inlier matches: the fraction of matches whose Sampson
(epipolar) distance under the final geometry is below a threshold.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mvgeo.epipolar import essential_from_pose, fundamental_from_essential, sampson_distance


@dataclass(frozen=True)
class PairCheck:
    """How well the final geometry explains one pair's verified matches."""

    i: int
    j: int
    n_matches: int
    explained_fraction: float
    rotation_deviation_deg: float = float("nan")


def pair_consistency(cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int],
                     matches: Sequence[tuple[int, int, np.ndarray]], *, threshold_px: float = 2.0
                     ) -> list[PairCheck]:
    """Per pair, the fraction of its matches within `threshold_px` Sampson distance of the final geometry.

    Args:
        cam_from_world: (N, 3, 4) final poses.
        focal_px: (N,) final focals, pixels of the images the matches live in.
        size_wh: (W, H) of those images (principal point at the centre).
        matches: (i, j, uv) with uv (M, 4) = (u_i, v_i, u_j, v_j), our pixel convention.
        threshold_px: Sampson distance limit in pixels.
    """
    W, H = size_wh
    out = []
    for i, j, uv in matches:
        Ri, ti = cam_from_world[i][:, :3], cam_from_world[i][:, 3]
        Rj, tj = cam_from_world[j][:, :3], cam_from_world[j][:, 3]
        R = Rj @ Ri.T
        t = tj - R @ ti
        Ki = np.array([[focal_px[i], 0, W / 2.0], [0, focal_px[i], H / 2.0], [0, 0, 1]])
        Kj = np.array([[focal_px[j], 0, W / 2.0], [0, focal_px[j], H / 2.0], [0, 0, 1]])
        if not np.linalg.norm(t) > 0:
            out.append(PairCheck(i, j, len(uv), 0.0))
            continue
        F = fundamental_from_essential(essential_from_pose(R, t / np.linalg.norm(t)), Ki, Kj)
        d = sampson_distance(F, uv[:, :2], uv[:, 2:])
        out.append(PairCheck(i, j, len(uv), float(np.mean(d < threshold_px)) if len(uv) else 0.0))
    return out


def pair_rotation_deviation(cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int],
                            matches: Sequence[tuple[int, int, np.ndarray]]) -> list[float]:
    """Per pair, the angle (deg) between the result's relative rotation and the one its matches imply.

    The Sampson check above cannot see a wrong relative rotation when the pair's
    epipolar geometry is nearly ambiguous (narrow field of view, few matches:
    rotation and depth relief trade off, the bas-relief ambiguity); the
    rotation the matches imply under the *final* focal (linear essential
    matrix, `mvgeo.align.loops.pose_from_matches`) can. nan where the matches
    determine no rotation (fewer than 8).
    """
    from mvgeo.align.loops import rotation_angle_deg, rotation_from_matches

    W, H = size_wh
    out = []
    for i, j, uv in matches:
        Ki = np.array([[focal_px[i], 0, W / 2.0], [0, focal_px[i], H / 2.0], [0, 0, 1]])
        Kj = np.array([[focal_px[j], 0, W / 2.0], [0, focal_px[j], H / 2.0], [0, 0, 1]])
        R_pair = rotation_from_matches(np.asarray(uv, np.float64), Ki, Kj)
        R_res = cam_from_world[j][:, :3] @ cam_from_world[i][:, :3].T
        out.append(float("nan") if R_pair is None else rotation_angle_deg(R_res @ R_pair.T))
    return out


def views_hinged(checks: Sequence[PairCheck], bad: Sequence[PairCheck], n_views: int) -> list[int]:
    """Views held by a single pair the result explains: views of the main group (`views_cut_off`'s; of at
    least three views) with exactly one explained pair.

    Such a view's pose rests on that one pair's relative pose. On a weak pair (a dozen matches, a narrow field
    of view) the rotation its matches imply can be 10-30 deg off while they still fit it (the bas-relief
    ambiguity), and nothing else checks it: measured on DTU scan24 at sigma 50/255 (noise seeds 0 and 1), a
    solution followed such a pair with its view 17.5 and 32 deg off and every pair explained but the view's
    others. The verdict asks PnP on the other views' points to confirm such views as it does cut-off ones.

    Returns:
        Sorted view indices.
    """
    bad_keys = {(c.i, c.j) for c in bad}
    judged = np.zeros(n_views, dtype=bool)
    degree = np.zeros(n_views, dtype=int)
    for c in checks:
        judged[[c.i, c.j]] = True
        if (c.i, c.j) not in bad_keys:
            degree[[c.i, c.j]] += 1
    cut = set(views_cut_off(checks, bad, n_views))
    main = [int(v) for v in np.flatnonzero(judged) if int(v) not in cut]
    if len(main) < 3:  # two views held by their one pair: nothing else to locate them on
        return []
    return [v for v in main if degree[v] == 1]


def views_cut_off(checks: Sequence[PairCheck], bad: Sequence[PairCheck], n_views: int) -> list[int]:
    """Views that are in at least one checked pair but are not linked to the main group of views through
    pairs the result explains.

    The pairs not in `bad` connect the views into groups; the main group is the one with the most views
    (then the most matches on its pairs, then the lowest view index). Every other judged view is cut
    off: the result contradicts every verified pair that links it, or its group, to the main group, so
    its placement relative to the main group is not supported by its matches (a single view whose every
    pair is contradicted, or a group hinged on contradicted pairs: a sparse orbit whose pair graph is a
    chain can be bent at one view with every other pair explained). However small the share of all
    matches those pairs hold (`AlignConfig.max_unexplained_fraction` judges the reconstruction as a
    whole), such views are not registered. Views in no checked pair are not judged here (the pair
    graph's connectivity is checked elsewhere).

    Args:
        checks: every checked pair (`pair_consistency`).
        bad: the checks that failed (a subset of `checks`).
        n_views: number of views; pair indices are below it.

    Returns:
        Sorted view indices.
    """
    parent = list(range(n_views))

    def root(v: int) -> int:
        while parent[v] != v:
            parent[v] = parent[parent[v]]
            v = parent[v]
        return v

    bad_keys = {(c.i, c.j) for c in bad}
    judged = np.zeros(n_views, dtype=bool)
    for c in checks:
        judged[[c.i, c.j]] = True
        if (c.i, c.j) not in bad_keys:
            parent[root(c.i)] = root(c.j)
    groups: dict[int, list[int]] = {}
    for v in np.flatnonzero(judged):
        groups.setdefault(root(int(v)), []).append(int(v))
    if len(groups) <= 1:
        return []
    matches = dict.fromkeys(groups, 0)
    for c in checks:
        if (c.i, c.j) not in bad_keys:
            matches[root(c.i)] += c.n_matches
    main = max(groups, key=lambda g: (len(groups[g]), matches[g], -min(groups[g])))
    return sorted(v for g, vs in groups.items() if g != main for v in vs)
