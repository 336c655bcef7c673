"""Rotation loop consistency of the pair graph: find verified pairs that contradict their loops.

A pair can pass two-view verification and still be false (repeated or
symmetric structure matched across the object): its matches agree with *a*
relative pose, just not the true one. Such a pair cannot be recognised
alone, but in a loop of pairs the relative rotations must compose to the
identity, R_ki R_jk R_ij = I (Zach, Klopschitz and Pollefeys 2010,
"Disambiguating visual relations using loop constraints"; the triplet
filtering of global SfM, e.g. 1DSfM and OpenMVG). We use the 3-loops
(triangles) of the graph and a greedy vote:

1. every triangle whose three pairs are all present is *consistent* when its
   loop rotation is within `max_loop_deg` of the identity, else *inconsistent*;
2. a pair is a suspect when it takes part in more inconsistent than
   consistent triangles;
3. the suspect with the largest margin (inconsistent minus consistent; ties:
   the weaker pair, by weight) is removed, the votes are recounted without
   it, and so on until no suspect is left.

Removing a pair whose triangle is still present never disconnects the
graph (the triangle's other two pairs connect its views). A pair that takes
part in no triangle (a bridge, or a longer loop only) cannot be judged here
and is kept.

Relative rotations come from each pair's inlier matches (linear essential
matrix with the current focal estimates, cheirality by triangulation) or,
for models without matches, from the pair's pointmap (PnP of view j's points,
which live in camera i's frame, against view j's pixel grid).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from mvgeo.common.deps import cv2
from mvgeo.epipolar import _hartley, project_to_essential
from mvgeo.pnp import sqpnp
from mvgeo.twoview import pose_from_essential

#: A loop of three pairs is consistent when its rotation is within this angle of the identity (degrees).
#: Three pair rotations with independent errors of sigma each give a loop error of about sqrt(3) sigma.
#: Measured with the focal the pipeline had before the bundle adjustment (on two scenes a prior 25 % and
#: 50 % off, as no pair determined it): true triangles 0.2 deg median / 0.8 deg max on llff_like (220
#: triangles), up to 5.2 deg on temple_sparse_ring and 5.7-7.4 deg on object_ring; triangles holding a false
#: pair 25-35 deg (temple) and 20-133 deg (object_ring). The one true triangle above 10 deg (temple,
#: 11.5 deg) holds a pair 14 deg off the calibrated poses, which the vote then removes.
DEFAULT_MAX_LOOP_DEG = 10.0


@dataclass
class LoopCheck:
    """Outcome of `reject_by_loops`.

    Attributes:
        removed: the rejected pairs (i < j), in the order they were removed.
        votes: per removed pair, (inconsistent, consistent) triangle counts when it was removed.
        n_triangles: triangles of the input graph.
        n_inconsistent: of those, inconsistent ones.
        loop_deg: (i, j, k) -> loop rotation error (degrees) of every triangle of the input graph.
    """

    removed: list[tuple[int, int]] = field(default_factory=list)
    votes: list[tuple[int, int]] = field(default_factory=list)
    n_triangles: int = 0
    n_inconsistent: int = 0
    loop_deg: dict[tuple[int, int, int], float] = field(default_factory=dict)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (0..180)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _rot(rel: Mapping[tuple[int, int], np.ndarray], a: int, b: int) -> np.ndarray:
    """cam_b_from_cam_a rotation from the (i < j) keyed map."""
    return rel[(a, b)] if (a, b) in rel else rel[(b, a)].T


def triangle_loops(rel: Mapping[tuple[int, int], np.ndarray]) -> dict[tuple[int, int, int], float]:
    """Loop error (degrees) of every triangle (i < j < k) whose three pairs are in `rel`.

    Args:
        rel: (i, j) with i < j -> cam_j_from_cam_i rotation (3, 3).
    """
    nbr: dict[int, set[int]] = {}
    for i, j in rel:
        nbr.setdefault(i, set()).add(j)
        nbr.setdefault(j, set()).add(i)
    out = {}
    for i, j in sorted(rel):
        for k in sorted(nbr[i] & nbr[j]):
            if k > j:
                loop = _rot(rel, k, i) @ _rot(rel, j, k) @ _rot(rel, i, j)
                out[(i, j, k)] = rotation_angle_deg(loop)
    return out


def reject_by_loops(rel: Mapping[tuple[int, int], np.ndarray], weights: Mapping[tuple[int, int], float] | None = None,
                    *, max_loop_deg: float = DEFAULT_MAX_LOOP_DEG) -> LoopCheck:
    """Greedy loop vote (module docstring): the pairs to reject.

    Args:
        rel: (i, j) with i < j -> cam_j_from_cam_i rotation.
        weights: (i, j) -> pair strength (e.g. inlier count); breaks ties
            (the weaker pair goes first). Default: all equal.
        max_loop_deg: consistency threshold of a triangle.
    """
    loops = triangle_loops(rel)
    check = LoopCheck(n_triangles=len(loops), n_inconsistent=sum(e > max_loop_deg for e in loops.values()),
                      loop_deg=loops)
    w = weights or {}
    live = dict(loops)
    while live:
        bad: dict[tuple[int, int], int] = {}
        good: dict[tuple[int, int], int] = {}
        for (i, j, k), err in live.items():
            tally = bad if err > max_loop_deg else good
            for e in ((i, j), (j, k), (i, k)):
                tally[e] = tally.get(e, 0) + 1
        suspects = [e for e in bad if bad[e] > good.get(e, 0)]
        if not suspects:
            break
        worst = max(suspects, key=lambda e: (bad[e] - good.get(e, 0), -w.get(e, 0.0), e))
        check.removed.append(worst)
        check.votes.append((bad[worst], good.get(worst, 0)))
        live = {t: err for t, err in live.items() if not {worst[0], worst[1]} <= set(t)}
    return check


def rotation_from_matches(uv: np.ndarray, K_i: np.ndarray, K_j: np.ndarray) -> np.ndarray | None:
    """cam_j_from_cam_i rotation that a pair's inlier matches (M, 4) imply, or None (< 8 matches)."""
    pose = pose_from_matches(uv, K_i, K_j)
    return None if pose is None else pose[0]


def essential_linear(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """`mvgeo.epipolar.essential_from_linear` (Hartley-normalised 8-point, rank 2, projected to E) with a thin SVD.

    Same result (tested); the reference's full SVD builds an (N, N) factor and took ~37 ms per pair of
    ~500 matches, this ~1 ms.
    """
    T1, n1 = _hartley(x1)
    T2, n2 = _hartley(x2)
    Q = np.einsum("ni,nj->nij", np.c_[n2, np.ones(len(n2))], np.c_[n1, np.ones(len(n1))]).reshape(-1, 9)
    Fn = np.linalg.svd(Q, full_matrices=False)[2][-1].reshape(3, 3)
    U, S, Vt = np.linalg.svd(Fn)
    F = T2.T @ (U @ np.diag([S[0], S[1], 0.0]) @ Vt) @ T1
    return project_to_essential(F / np.linalg.norm(F))


#: The cheirality vote that picks among E's decompositions uses at most this many matches (evenly spread).
CHEIRALITY_POINTS = 200


def pose_from_matches(uv: np.ndarray, K_i: np.ndarray, K_j: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """cam_j_from_cam_i (R, unit t) from a pair's inlier matches (M, 4): linear essential matrix + cheirality."""
    if len(uv) < 8:
        return None
    h = np.concatenate([uv[:, :2], np.ones((len(uv), 1))], axis=1)
    x1 = (h @ np.linalg.inv(K_i).T)[:, :2]
    h[:, :2] = uv[:, 2:]
    x2 = (h @ np.linalg.inv(K_j).T)[:, :2]
    E = essential_linear(x1, x2)
    if not np.all(np.isfinite(E)):
        return None
    sub = np.linspace(0, len(uv) - 1, min(len(uv), CHEIRALITY_POINTS)).round().astype(int)
    R, t, front, _ = pose_from_essential(E, x1[sub], x2[sub])
    return (R, t) if front.any() else None


def rotation_from_pointmap(pts_j_in_i: np.ndarray, conf_j: np.ndarray, focal_j_px: float) -> np.ndarray | None:
    """cam_j_from_cam_i rotation by PnP of view j's pointmap (in camera i's frame) on j's pixel grid."""
    H, W = conf_j.shape
    ok = (conf_j > 1.0) & np.all(np.isfinite(pts_j_in_i), axis=-1)
    rows, cols = np.nonzero(ok)
    if len(rows) < 6:
        return None
    uv = np.stack([cols, rows], axis=1).astype(np.float64)  # OpenCV pixel centres at integers
    K = np.array([[focal_j_px, 0, W / 2.0 - 0.5], [0, focal_j_px, H / 2.0 - 0.5], [0, 0, 1]])
    okp, rvec, _ = sqpnp(pts_j_in_i[ok].astype(np.float64), uv, K)
    return cv2.Rodrigues(rvec)[0] if okp else None


def pair_rotations(matches: Sequence[tuple[int, int, np.ndarray]], K_align: np.ndarray, preds: Sequence = ()
                   ) -> tuple[dict[tuple[int, int], np.ndarray], dict[tuple[int, int], float]]:
    """Relative rotation and weight (number of matches or confident pixels) of every pair we can.

    Args:
        matches: (i, j, uv) inlier matches at the alignment resolution (preferred).
        K_align: (N, 3, 3) intrinsics at that resolution.
        preds: `PairPrediction`s; used for pairs without matches (pointmap PnP).
    """
    rel: dict[tuple[int, int], np.ndarray] = {}
    weight: dict[tuple[int, int], float] = {}
    for i, j, uv in matches:
        R = rotation_from_matches(np.asarray(uv, np.float64), K_align[i], K_align[j])
        if R is not None:
            key, R = ((i, j), R) if i < j else ((j, i), R.T)
            rel[key], weight[key] = R, float(len(uv))
    for p in preds:
        key = (min(p.i, p.j), max(p.i, p.j))
        if key in rel:
            continue
        R = rotation_from_pointmap(np.asarray(p.pts_j, np.float64), p.conf_j,
                                   float(p.focal_j_px if p.focal_j_px is not None else p.focal_i_px))
        if R is not None:
            rel[key] = R if p.i < p.j else R.T
            weight[key] = float(np.count_nonzero(p.conf_j > 1.0))
    return rel, weight


def all_triangles(n: int, edges: Sequence[tuple[int, int]]) -> list[tuple[int, int, int]]:
    """Triangles (i < j < k) of an undirected graph (reference for `triangle_loops`' enumeration)."""
    es = {(min(a, b), max(a, b)) for a, b in edges}
    return [t for t in itertools.combinations(range(n), 3)
            if (t[0], t[1]) in es and (t[1], t[2]) in es and (t[0], t[2]) in es]
