"""Robust rotation averaging: global camera rotations from the verified pairs' relative rotations.

Chaining relative rotations along a spanning tree (DUSt3R's initialisation, `pose_chain`) adds up their
errors around every loop: on an orbit the last pair closing the ring carries the whole drift. Rotation
averaging spreads it over all pairs instead (the first stage of global SfM: Theia, GLOMAP):

1. chordal initialisation: the linear least-squares solution of ``R_j = R_ji R_i`` over all pairs
   (9 equations per pair, ``R_0 = I`` fixed), each 3x3 block projected onto SO(3) (Martinec & Pajdla 2007);
2. robust refinement in the tangent space (Chatterjee & Govindu 2013, "Efficient and robust large-scale
   rotation averaging"): with left perturbations ``R_k <- exp([w_k]) R_k`` the residual of pair (i, j) is
   linear, ``w_j - (R_j R_i^T) w_i = log(R_ji R_i R_j^T)``; each iteration solves the weighted linear
   least-squares problem with iteratively reweighted weights of a Cauchy-like loss
   (``1 / (1 + (r / scale)^2)`` times the pair's own weight), so that a few wrong pairs do not bend the
   others.

Rotations are ``cam_from_world`` (docs/conventions.md); relative rotations ``cam_j_from_cam_i``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mvgeo.align.graph import components
from mvgeo.align.loops import pair_rotations
from mvgeo.align.pairs import PairPrediction
from mvgeo.align.pointmap_geometry import AlignInit
from mvgeo.align.pose_chain import init_from_pair_poses, pair_pose_from_pointmap
from mvgeo.common.errors import DegenerateGeometryError

__all__ = ["RotationAveragingResult", "average_rotations", "init_from_averaged_rotations",
           "relative_rotation_residuals_deg"]


@dataclass(frozen=True)
class RotationAveragingResult:
    """Global rotations and how well they explain each pair.

    Attributes:
        R_cam_from_world: (N, 3, 3) rotations, view 0 at the identity.
        residual_deg: {(i, j): angle between the pair's rotation and ``R_j R_i^T``} in degrees.
        iterations: refinement iterations run.
    """

    R_cam_from_world: np.ndarray
    residual_deg: dict[tuple[int, int], float]
    iterations: int


def _project_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def relative_rotation_residuals_deg(R_cam_from_world: np.ndarray,
                                    rel: Mapping[tuple[int, int], np.ndarray]) -> dict[tuple[int, int], float]:
    """Per pair (i, j): angle (deg) of ``R_ji^T R_j R_i^T``, the disagreement of the pair with the global rotations."""
    out = {}
    for (i, j), R_ji in rel.items():
        E = R_ji.T @ R_cam_from_world[j] @ R_cam_from_world[i].T
        out[(i, j)] = float(np.degrees(Rotation.from_matrix(E).magnitude()))  # precise near 0, unlike arccos
    return out


def _chordal(n: int, edges: list[tuple[int, int]], Rs: list[np.ndarray], w: np.ndarray) -> np.ndarray:
    """Linear least squares for the stacked 3x3 blocks (R_0 fixed to I), then projection onto SO(3)."""
    # Unknowns: the 9 entries of R_1..R_{n-1}, row-major; R_j - R_ji R_i = 0 column by column.
    m = len(edges)
    A = np.zeros((9 * m, 9 * (n - 1)))
    b = np.zeros(9 * m)
    for e, ((i, j), R_ji) in enumerate(zip(edges, Rs, strict=True)):
        sw = np.sqrt(w[e])
        for c in range(3):  # column c: R_j[:, c] - R_ji @ R_i[:, c] = 0
            rows = slice(9 * e + 3 * c, 9 * e + 3 * c + 3)
            if j > 0:
                A[rows, [9 * (j - 1) + 3 * r + c for r in range(3)]] += sw * np.eye(3)
            else:
                b[rows] -= sw * np.eye(3)[:, c]
            if i > 0:
                A[rows, [9 * (i - 1) + 3 * r + c for r in range(3)]] -= sw * R_ji
            else:
                b[rows] += sw * R_ji[:, c]
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    out = np.empty((n, 3, 3))
    out[0] = np.eye(3)
    for k in range(1, n):
        out[k] = _project_so3(x[9 * (k - 1):9 * k].reshape(3, 3))
    return out


def average_rotations(n_views: int, rel: Mapping[tuple[int, int], np.ndarray],
                      weight: Mapping[tuple[int, int], float] | None = None, *, robust_scale_deg: float = 2.0,
                      max_iters: int = 20, tol_deg: float = 1e-4) -> RotationAveragingResult:
    """Global rotations from relative ones (module docstring).

    Args:
        n_views: number of views N.
        rel: {(i, j): R_ji (3, 3)} cam_j_from_cam_i of each pair (i != j).
        weight: {(i, j): w > 0} per pair (e.g. its inlier count); default 1.
        robust_scale_deg: residual at which a pair's weight is halved in the refinement.
        max_iters: refinement iterations at most.
        tol_deg: the refinement stops when no rotation moves by more than this.

    Returns:
        `RotationAveragingResult` with view 0 at the identity.

    Raises:
        DegenerateGeometryError: the pairs do not connect all views.
    """
    edges = [(int(i), int(j)) for i, j in rel]
    if len(components(n_views, edges)) != 1:
        raise DegenerateGeometryError(f"rotation averaging: the {len(edges)} pairs do not connect the {n_views} views")
    Rs = [np.asarray(rel[e], np.float64) for e in rel]
    w0 = np.array([float(weight[e]) if weight is not None else 1.0 for e in rel])
    if not np.all(w0 > 0):
        raise DegenerateGeometryError("rotation averaging: pair weights must be positive")
    w0 = w0 / w0.max()
    R = _chordal(n_views, edges, Rs, w0)
    scale = np.radians(robust_scale_deg)
    iterations = 0
    for iterations in range(1, max_iters + 1):  # noqa: B007  (the count is returned)
        m = len(edges)
        A = np.zeros((3 * m, 3 * (n_views - 1)))
        r = np.zeros(3 * m)
        for e, ((i, j), R_ji) in enumerate(zip(edges, Rs, strict=True)):
            rows = slice(3 * e, 3 * e + 3)
            r[rows] = Rotation.from_matrix(R_ji @ R[i] @ R[j].T).as_rotvec()
            if j > 0:
                A[rows, 3 * (j - 1):3 * j] = np.eye(3)
            if i > 0:
                A[rows, 3 * (i - 1):3 * i] = -(R[j] @ R[i].T)
        res = np.linalg.norm(r.reshape(-1, 3), axis=1)
        sw = np.sqrt(w0 / (1.0 + (res / scale) ** 2))
        x = np.linalg.lstsq(A * np.repeat(sw, 3)[:, None], r * np.repeat(sw, 3), rcond=None)[0]
        step = x.reshape(-1, 3)
        for k in range(1, n_views):
            R[k] = Rotation.from_rotvec(step[k - 1]).as_matrix() @ R[k]
        if np.degrees(np.max(np.linalg.norm(step, axis=1), initial=0.0)) < tol_deg:
            break
    return RotationAveragingResult(R, relative_rotation_residuals_deg(R, rel), iterations)


def init_from_averaged_rotations(preds: Sequence[PairPrediction], matches: Sequence[tuple[int, int, np.ndarray]],
                                 sizes_hw: Sequence[tuple[int, int]], focal_px: np.ndarray, align_px_per_grid: float,
                                 align_size_wh: tuple[int, int]) -> AlignInit:
    """`pose_chain.init_from_pair_poses` with every chained rotation taken from the averaged global rotations.

    The relative rotations of all verified pairs (from their inlier matches, `loops.pair_rotations`; from
    the pointmap where a pair has none) are averaged (`average_rotations`, weights = matches); each chained
    pair then gets ``R_j R_i^T`` of the averaged rotations with its own pointmap's translation direction, so
    the ring's drift is spread over all pairs instead of landing on the pairs that close it. Positions and
    depths chain as in `init_from_pair_poses`.

    Args:
        preds: the pairs' pointmaps; matches: (i, j, (M, 4) inlier matches at the alignment resolution).
        sizes_hw: pointmap grid sizes; focal_px: (N,) focal per view on the pointmap grid.
        align_px_per_grid: alignment pixels per pointmap pixel; align_size_wh: alignment image size.

    Raises:
        DegenerateGeometryError: the pairs with a rotation do not connect the views, or the chaining fails.
    """
    n = len(sizes_hw)
    W, H = align_size_wh
    K = np.array([[[f * align_px_per_grid, 0.0, W / 2.0], [0.0, f * align_px_per_grid, H / 2.0], [0.0, 0.0, 1.0]]
                  for f in focal_px])
    rel, weight = pair_rotations(matches, K, preds)
    R = average_rotations(n, rel, weight).R_cam_from_world
    override = {}
    for p in preds:
        pose = pair_pose_from_pointmap(p, float(focal_px[p.j]))
        if pose is not None:
            override[(p.i, p.j)] = (R[p.j] @ R[p.i].T, pose[1])
    return init_from_pair_poses(preds, sizes_hw, focal_init_px=focal_px, rel_override=override)
