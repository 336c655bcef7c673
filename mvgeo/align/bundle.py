"""Sparse bundle adjustment on the pairwise feature matches (scipy `least_squares`, sparse Jacobian).

Each inlier match of a pair is one two-view point (no track merging), so the
problem is: per view a pose `cam_from_world` (rotation vector, translation),
a shared focal or one per view (log, pixels; principal point fixed at the
centre), and per match a world point. Residuals are reprojection errors in
pixels at the alignment resolution with a Huber loss. The gauge (7 dof) is
left free; the trust-region solver copes with the rank deficiency.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from mvgeo.triangulate import TriangulationCriteria, triangulate_two_view

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BundleConfig:
    """Options of `bundle_adjust`.

    Attributes:
        huber_px: Huber loss scale (pixels).
        max_nfev: function evaluations of `least_squares`.
        shared_focal: one focal for all views.
        optimize_focal: False keeps the focals fixed (known intrinsics).
        max_points: at most this many matches (evenly subsampled) enter the problem.
    """

    huber_px: float = 1.0
    max_nfev: int = 200
    shared_focal: bool = True
    optimize_focal: bool = True
    max_points: int = 20000


@dataclass
class BundleResult:
    """Refined poses/focals and the reprojection error before and after (pixels, alignment resolution)."""

    cam_from_world: np.ndarray  # (N, 3, 4)
    focal_px: np.ndarray  # (N,)
    n_points: int
    n_observations: int
    reproj_rms_before_px: float
    reproj_rms_after_px: float
    reproj_median_before_px: float
    reproj_median_after_px: float


def bundle_adjust(cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int],
                  matches: Sequence[tuple[int, int, np.ndarray]], *, config: BundleConfig = BundleConfig()
                  ) -> BundleResult:
    """Refine poses and focals on two-view matches.

    Args:
        cam_from_world: (N, 3, 4) initial poses.
        focal_px: (N,) initial focals (pixels at `size_wh`).
        size_wh: (W, H) of the images the matches are measured in.
        matches: (i, j, uv) with uv (M, 4) = (u_i, v_i, u_j, v_j), our pixel convention.
        config: options.
    """
    n = len(cam_from_world)
    W, H = size_wh
    c = np.array([W / 2.0, H / 2.0])
    obs_view, obs_point, obs_uv, points = [], [], [], []
    crit = TriangulationCriteria(min_angle_deg=1.0, max_angular_error_deg=1.0)
    total = sum(len(m[2]) for m in matches)
    stride = max(1, int(np.ceil(total / config.max_points)))
    for i, j, uv in matches:
        uv = uv[::stride]
        Ri, ti = cam_from_world[i][:, :3], cam_from_world[i][:, 3]
        Rj, tj = cam_from_world[j][:, :3], cam_from_world[j][:, 3]
        rays_i = np.concatenate([(uv[:, :2] - c) / focal_px[i], np.ones((len(uv), 1))], 1)
        rays_j = np.concatenate([(uv[:, 2:] - c) / focal_px[j], np.ones((len(uv), 1))], 1)
        j_from_i = np.concatenate([Rj @ Ri.T, (tj - Rj @ Ri.T @ ti)[:, None]], 1)
        tri = triangulate_two_view(rays_i, rays_j, j_from_i, criteria=crit)
        ok = tri.valid
        X = (tri.points[ok] - ti) @ Ri  # world
        ids = sum(len(p) for p in points) + np.arange(len(X))
        points.append(X)
        obs_view += [np.full(len(X), i), np.full(len(X), j)]
        obs_point += [ids, ids]
        obs_uv += [uv[ok, :2], uv[ok, 2:]]
    X0 = np.concatenate(points) if points else np.zeros((0, 3))
    ov, op, ouv = np.concatenate(obs_view), np.concatenate(obs_point), np.concatenate(obs_uv)
    P = len(X0)
    nf = 1 if config.shared_focal else n
    f_index = np.zeros(n, np.int64) if config.shared_focal else np.arange(n)
    rv0 = Rotation.from_matrix(cam_from_world[:, :, :3]).as_rotvec()
    logf0 = np.log(np.exp(np.mean(np.log(focal_px))) * np.ones(1)) if config.shared_focal else np.log(focal_px)

    def unpack(x):
        rv = x[:3 * n].reshape(n, 3)
        t = x[3 * n:6 * n].reshape(n, 3)
        if config.optimize_focal:
            lf, rest = x[6 * n:6 * n + nf], x[6 * n + nf:]
        else:
            lf, rest = logf0, x[6 * n:]
        return rv, t, lf, rest.reshape(P, 3)

    def residuals(x):
        rv, t, lf, Xw = unpack(x)
        R = Rotation.from_rotvec(rv[ov]).as_matrix()
        xc = np.einsum("mij,mj->mi", R, Xw[op]) + t[ov]
        f = np.exp(lf)[f_index[ov]]
        z = np.where(np.abs(xc[:, 2]) < 1e-9, 1e-9, xc[:, 2])
        proj = f[:, None] * xc[:, :2] / z[:, None] + c
        return (proj - ouv).reshape(-1)

    x0 = np.concatenate([rv0.reshape(-1), cam_from_world[:, :, 3].reshape(-1)]
                        + ([logf0] if config.optimize_focal else []) + [X0.reshape(-1)])
    r0 = residuals(x0).reshape(-1, 2)
    e0 = np.linalg.norm(r0, axis=1)
    if P < 10:
        _log.warning("bundle adjustment skipped: only %d triangulated matches", P)
        return BundleResult(cam_from_world.copy(), np.asarray(focal_px, float).copy(), P, len(ov),
                            *(float(np.sqrt(np.mean(e0**2))) if len(e0) else np.nan,) * 2,
                            *(float(np.median(e0)) if len(e0) else np.nan,) * 2)
    # Jacobian sparsity: each residual pair depends on its view's pose, its focal, its point.
    m = len(ov)
    nx = len(x0)
    S = lil_matrix((2 * m, nx), dtype=np.int8)
    rows = np.arange(m)
    pt0 = 6 * n + (nf if config.optimize_focal else 0)
    for k in range(2):
        r = 2 * rows + k
        for d in range(3):
            S[r, 3 * ov + d] = 1
            S[r, 3 * n + 3 * ov + d] = 1
            S[r, pt0 + 3 * op + d] = 1
        if config.optimize_focal:
            S[r, 6 * n + f_index[ov]] = 1
    sol = least_squares(residuals, x0, jac_sparsity=S.tocsr(), loss="huber", f_scale=config.huber_px,
                        max_nfev=config.max_nfev, x_scale="jac", method="trf", tr_solver="lsmr", verbose=0)
    rv, t, lf, _ = unpack(sol.x)
    e1 = np.linalg.norm(sol.fun.reshape(-1, 2), axis=1)
    out = np.concatenate([Rotation.from_rotvec(rv).as_matrix(), t[:, :, None]], axis=2)
    res = BundleResult(out, np.exp(lf)[f_index], P, m, float(np.sqrt(np.mean(e0**2))), float(np.sqrt(np.mean(e1**2))),
                       float(np.median(e0)), float(np.median(e1)))
    _log.info("bundle adjustment: %d points, reprojection RMS %.3g -> %.3g px (median %.3g -> %.3g)", P,
              res.reproj_rms_before_px, res.reproj_rms_after_px, res.reproj_median_before_px,
              res.reproj_median_after_px)
    return res
