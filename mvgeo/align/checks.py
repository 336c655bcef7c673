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
    """How well the final geometry explains one pair's verified matches: the fraction within the Sampson
    threshold, the result's relative rotation's angle from the one they imply (`pair_rotation_deviation`), and
    how well they pin the relative rotation at the result's pose (`pair_rotation_std`; nan: not measured)."""

    i: int
    j: int
    n_matches: int
    explained_fraction: float
    rotation_deviation_deg: float = float("nan")
    rotation_std_deg: float = float("nan")


def _pair_geometry(cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int], i: int, j: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The result's cam_j_from_cam_i (R (3, 3), t (3,)) and the two views' calibrations (principal point at
    the centre of `size_wh`)."""
    W, H = size_wh
    R = cam_from_world[j][:, :3] @ cam_from_world[i][:, :3].T
    t = cam_from_world[j][:, 3] - R @ cam_from_world[i][:, 3]
    Ki = np.array([[focal_px[i], 0, W / 2.0], [0, focal_px[i], H / 2.0], [0, 0, 1]])
    Kj = np.array([[focal_px[j], 0, W / 2.0], [0, focal_px[j], H / 2.0], [0, 0, 1]])
    return R, t, Ki, Kj


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
    out = []
    for i, j, uv in matches:
        R, t, Ki, Kj = _pair_geometry(cam_from_world, focal_px, size_wh, i, j)
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

    out = []
    for i, j, uv in matches:
        R_res, _, Ki, Kj = _pair_geometry(cam_from_world, focal_px, size_wh, i, j)
        R_pair = rotation_from_matches(np.asarray(uv, np.float64), Ki, Kj)
        out.append(float("nan") if R_pair is None else rotation_angle_deg(R_res @ R_pair.T))
    return out


def pair_rotation_std(cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int],
                      matches: Sequence[tuple[int, int, np.ndarray]], *, threshold_px: float = 2.0) -> list[float]:
    """Per pair, how well its matches within `threshold_px` pin the relative rotation at the result's pose: the
    largest standard deviation in degrees (`mvgeo.twoview.relative_rotation_std_deg`); principal point at the
    centre."""
    from mvgeo.twoview import relative_rotation_std_deg

    out = []
    for i, j, uv in matches:
        uv = np.asarray(uv, np.float64)
        R, t, Ki, Kj = _pair_geometry(cam_from_world, focal_px, size_wh, i, j)
        if not np.linalg.norm(t) > 0 or len(uv) < 6:
            out.append(float("inf"))
            continue
        out.append(relative_rotation_std_deg(uv[:, :2], uv[:, 2:], Ki, Kj, R, t, inlier_px=threshold_px))
    return out


#: A group of views joined to the others by a single explained pair is hinged on it when that pair's matches
#: pin its relative rotation no better than this at three standard deviations (`PairCheck.rotation_std_deg`):
#: the alignment's contract, no view more than 5 deg off.
HINGE_MAX_ROTATION_DEG = 5.0


@dataclass(frozen=True)
class Hinge:
    """A view, or a group of views, whose placement rests on one explained pair (`hinges`): the views (sorted
    indices) and that pair's check (its matches, and how well they pin the rotation)."""

    views: tuple[int, ...]
    pair: PairCheck


def views_hinged(checks: Sequence[PairCheck], bad: Sequence[PairCheck], n_views: int) -> list[int]:
    """The views of `hinged_groups`, sorted."""
    return sorted({v for g in hinged_groups(checks, bad, n_views) for v in g})


def hinged_groups(checks: Sequence[PairCheck], bad: Sequence[PairCheck], n_views: int) -> list[tuple[int, ...]]:
    """The views of each of `hinges` (sorted view indices), singles first."""
    return [h.views for h in hinges(checks, bad, n_views)]


def hinges(checks: Sequence[PairCheck], bad: Sequence[PairCheck], n_views: int) -> list[Hinge]:
    """Views whose placement rests on a single pair the result explains, in the main group (`views_cut_off`'s;
    of at least three views): each view with exactly one explained pair, alone, and each group of views joined
    to the others by one weak explained pair (a bridge of the graph of explained pairs whose matches pin its
    relative rotation no better than `HINGE_MAX_ROTATION_DEG` at three standard deviations; nan: not measured,
    weak): the smaller side of it; each with that pair.

    Such views' placement rests on that one pair's relative pose. On a weak pair (a dozen matches, a narrow
    field of view) the rotation its matches imply can be 10-30 deg off while they still fit it (the bas-relief
    ambiguity), and nothing else checks it: measured on DTU scan24 at sigma 50/255 (noise seeds 0 and 1), a
    solution followed such a pair with its view 17.5 and 32 deg off and every pair explained but the view's
    others; and (noise seed 1, no EXIF focal, the images dithered) four views joined to the other eight by one
    12-match pair (rotation standard deviation 1.9 deg) came back turned 14-19 deg as a block, every pair among
    them explained. The verdict asks PnP on the other views' points to confirm them (`unconfirmed_hinges`).
    A strong bridge is no hinge for a group: on the temple ring, broken at one contradicted pair, pairs of
    73-236 matches (0.3-0.6 deg) join groups that PnP on the black background cannot confirm.

    The smaller side: fewer views, then fewer matches on its explained pairs, then the side without the lowest
    view index.

    Returns:
        The hinges, singles first, then by their views.
    """
    bad_keys = {(c.i, c.j) for c in bad}
    cut = set(views_cut_off(checks, bad, n_views))
    judged = sorted({v for c in checks for v in (c.i, c.j)} - cut)
    if len(judged) < 3:  # two views held by their one pair: nothing else to locate them on
        return []
    edges = [c for c in checks if (c.i, c.j) not in bad_keys and c.i not in cut and c.j not in cut]
    found: dict[tuple[int, ...], PairCheck] = {}
    for k in bridges(n_views, [(c.i, c.j) for c in edges]):
        rest = [(c.i, c.j, c.n_matches) for m, c in enumerate(edges) if m != k]
        sides = (_reachable(edges[k].i, rest), _reachable(edges[k].j, rest))
        inner = [sum(n for i, j, n in rest if i in vs and j in vs) for vs in sides]
        side = min(zip(sides, inner, strict=True), key=lambda x: (len(x[0]), x[1], -min(x[0])))[0]
        if len(side) == 1 or _weak(edges[k]):
            found.setdefault(tuple(sorted(side)), edges[k])
    return [Hinge(g, found[g]) for g in sorted(found, key=lambda g: (len(g), g))]


def _weak(c: PairCheck) -> bool:
    """The pair's matches pin its relative rotation no better than `HINGE_MAX_ROTATION_DEG` at three standard
    deviations (nan: not measured, weak)."""
    return not 3.0 * c.rotation_std_deg <= HINGE_MAX_ROTATION_DEG


def unconfirmed_hinges(checks: Sequence[PairCheck], bad: Sequence[PairCheck], n_views: int,
                       located: Sequence[int] = (), misplaced: Sequence[int] = ()) -> list[Hinge]:
    """The `hinges` that PnP on the other views' points (`mvgeo.align.locate`) does not confirm, each with its
    unconfirmed views: a single view unless it is `located`; a group's views, less the located ones, unless at
    least one of them is located and none is `misplaced` (PnP puts it confidently elsewhere)."""
    ok, off = set(located), set(misplaced)
    out = []
    for h in hinges(checks, bad, n_views):
        g = set(h.views)
        confirmed = len(g) > 1 and bool(ok & g) and not (off & g)
        if not confirmed and g - ok:
            out.append(Hinge(tuple(sorted(g - ok)), h.pair))
    return out


def unconfirmed_hinged(checks: Sequence[PairCheck], bad: Sequence[PairCheck], n_views: int,
                       located: Sequence[int] = (), misplaced: Sequence[int] = ()) -> list[int]:
    """The views of `unconfirmed_hinges`, sorted."""
    return sorted({v for h in unconfirmed_hinges(checks, bad, n_views, located, misplaced) for v in h.views})


def bridges(n_vertices: int, edges: Sequence[tuple[int, int]]) -> list[int]:
    """Indices of the bridges of an undirected graph (edges whose removal disconnects their endpoints), by
    Tarjan's low-link depth-first search (iterative; O(V + E)). Parallel edges are not bridges.

    Args:
        n_vertices: vertices are 0..n_vertices-1; edges: (i, j) pairs, i != j.
    """
    adj: list[list[tuple[int, int]]] = [[] for _ in range(n_vertices)]
    for k, (i, j) in enumerate(edges):
        adj[i].append((j, k))
        adj[j].append((i, k))
    order = [-1] * n_vertices
    low = [0] * n_vertices
    out: list[int] = []
    counter = 0
    for root in range(n_vertices):
        if order[root] >= 0 or not adj[root]:
            continue
        order[root] = low[root] = counter
        counter += 1
        stack = [(root, -1, iter(adj[root]))]  # (vertex, the edge it was reached by, its remaining edges)
        while stack:
            v, via, it = stack[-1]
            for w, k in it:
                if k == via:
                    continue
                if order[w] < 0:
                    order[w] = low[w] = counter
                    counter += 1
                    stack.append((w, k, iter(adj[w])))
                    break
                low[v] = min(low[v], order[w])
            else:
                stack.pop()
                if stack:
                    u = stack[-1][0]
                    low[u] = min(low[u], low[v])
                    if low[v] > order[u]:
                        out.append(via)
    return sorted(out)


def _reachable(start: int, edges: Sequence[tuple[int, int, int]]) -> set[int]:
    """The views joined to `start` by `edges` ((i, j, matches)), `start` included."""
    nbrs: dict[int, list[int]] = {}
    for i, j, _ in edges:
        nbrs.setdefault(i, []).append(j)
        nbrs.setdefault(j, []).append(i)
    seen, stack = {start}, [start]
    while stack:
        for w in nbrs.get(stack.pop(), ()):
            if w not in seen:
                seen.add(w)
                stack.append(w)
    return seen


def views_cut_off(checks: Sequence[PairCheck], bad: Sequence[PairCheck], n_views: int, *,
                  located: Sequence[int] = (), misplaced: Sequence[int] = ()) -> list[int]:
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

    A view in `located` is linked to the main group by other evidence: PnP on the main group's points puts
    it where the result does (`mvgeo.align.locate`); it is not cut off. Nor is the rest of its group, joined
    to it by explained pairs, unless PnP puts one of the group's views confidently elsewhere (`misplaced`: a
    block turned as a whole, as `unconfirmed_hinges` asks): the explained pairs place the group on the
    located view as they place the main group's views on each other; a part of the group that hangs on the
    rest by a weak bridge needs a located view of its own (`_located_parts`; single views held by one strong
    pair are not examined: `hinges` looks at the main group only). Measured on object_ring (28 of 32
    views, dither seed 2): the ring broken at two held-out views, both gaps crossed only by weak pairs
    (13-24 matches) whose matches imply rotations 13-36 deg off while the result is within 0.9 deg of the
    truth; PnP located view_023 at the far end of the 14-view group (31 inliers, 0.49 deg from the result).

    Args:
        checks: every checked pair (`pair_consistency`).
        bad: the checks that failed (a subset of `checks`).
        n_views: number of views; pair indices are below it.
        located: views PnP locates where the result puts them (`Located.ok`).
        misplaced: views PnP locates confidently elsewhere (`Located.placed_elsewhere`).

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
    ok, off = set(located), {root(v) for v in misplaced if judged[v]}
    linked: set[int] = set()
    for g in {root(v) for v in ok if judged[v]} - off - {main}:
        linked |= _located_parts(groups[g], [c for c in checks if (c.i, c.j) not in bad_keys and root(c.i) == g], ok)
    return sorted(v for g, vs in groups.items() if g != main for v in vs if v not in ok and v not in linked)


def _located_parts(views: Sequence[int], edges: Sequence[PairCheck], located: set[int]) -> set[int]:
    """The views of a group in a part that holds a located view, the parts being what the group's weak bridges
    separate. `edges`: the group's explained pairs; a weak bridge: a bridge that `_weak` judges, as `hinges`
    does."""
    index = {v: k for k, v in enumerate(views)}
    local = [(index[c.i], index[c.j]) for c in edges]
    weak = {k for k in bridges(len(views), local) if _weak(edges[k])}
    rest = [(views[a], views[b], 0) for k, (a, b) in enumerate(local) if k not in weak]
    out, unplaced = set(), set(views)
    while unplaced:
        part = _reachable(min(unplaced), rest)
        if part & located:
            out |= part
        unplaced -= part
    return out
