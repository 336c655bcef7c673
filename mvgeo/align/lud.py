"""The LUD start of global positioning (`mvgeo.align.translation_averaging`): camera centres and track points
from fixed rotations that cannot collapse onto one point, as a start for the bounded-angle refinement."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix, diags

__all__ = ["lud_positions"]


def lud_positions(rays: np.ndarray, obs_view: np.ndarray, obs_point: np.ndarray, n_views: int, n_points: int,
                  iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 3) and points (P, 3) of the LUD problem, the start of the BATA refinement.

    LUD (Ozyesil & Singer 2015, "least unsquared deviations", here camera-to-point): minimise
    ``sum_k |X_p - C_n - d_k v_k|`` subject to ``d_k >= 1``. The bound keeps the solution from collapsing
    onto one point (which the scale-free BATA cost cannot prevent from a poor start) and the unsquared norm
    limits the pull of wrong observations. The problem is convex; a start needs no exact solution, so it runs
    a fixed number of alternations of (a) the weighted least squares in (C, X) for fixed d, X eliminated per
    track, leaving an (N, N) system per axis whose null space (a common translation) is fixed by a centroid
    term, (b) ``d_k = max(1, v_k . w_k)``, (c) the IRLS weights ``1 / |r_k|`` of the unsquared norm.

    The incidence products are sums per view and per point (`np.bincount`) and one sparse (views, points)
    matrix of the weights, instead of the four scipy.sparse incidence products of the textbook form
    (`tests/mvgeo/align/test_translation_averaging.py::_lud_reference`, tested equal; 0.18 s of 2.7 s on
    the temple ring's averaged start, 3-6x slower than this at 100-400 views).
    """
    k = len(rays)
    d, weight = np.ones(k), np.ones(k)
    for _ in range(iterations):
        wb = weight[:, None] * (d[:, None] * rays)
        w_view = np.bincount(obs_view, weight, minlength=n_views)
        w_point = np.bincount(obs_point, weight, minlength=n_points)
        # r = X[p] - C[n] - d v: the normal equations' (C, C) block is diag(w_view), the (C, X) block -M
        # (a repeated observation adds to its (view, point) cell: the COO -> CSR conversion sums them).
        M = coo_matrix((weight, (obs_view, obs_point)), shape=(n_views, n_points)).tocsr()
        M_by_point = M @ diags(1.0 / w_point)
        S = (np.diag(w_view) - (M_by_point @ M.T).toarray()
             + np.full((n_views, n_views), weight.sum() / (k * n_views)))
        BWb = np.stack([np.bincount(obs_point, wb[:, c], minlength=n_points) for c in range(3)], axis=1)
        AWb = -np.stack([np.bincount(obs_view, wb[:, c], minlength=n_views) for c in range(3)], axis=1)
        C = np.linalg.solve(S, AWb + M_by_point @ BWb)
        X = (BWb + M.T @ C) / w_point[:, None]
        w = X[obs_point] - C[obs_view]
        d = np.maximum(1.0, np.sum(w * rays, axis=1))
        r = np.linalg.norm(w - d[:, None] * rays, axis=1)
        weight = 1.0 / np.maximum(r, 1e-6 * max(float(np.median(r)), 1e-300))
    return C, X
