"""Sparse bundle adjustment on feature tracks (own LM with the Schur complement; scipy reference).

Tracks: the pairs' inlier matches are merged by keypoint (a keypoint is
identified by its view and its exact pixel coordinates, which come from one
SIFT run per image); tracks that would hold two keypoints of one view are
dropped. Unknowns: per view a pose `cam_from_world` (rotation vector,
translation), a shared focal or one per view (log, pixels; principal point
fixed at the centre), and per track a world point (multi-view triangulation
from the aligned poses). Residuals are reprojection errors in pixels at the
alignment resolution with a Huber loss; after a first solve, observations
with an error above `max_reproj_px` are removed and the problem is solved
again (COLMAP's filter-and-repeat). The first view's pose is held fixed.
The default solver is `mvgeo.align.bundle_lm` (the LM damping holds the scale
gauge). The scipy `least_squares` path (sparse finite-difference Jacobian,
LSMR steps) is the slow reference; it holds the scale with one extra residual
(distance between the first two camera centres): with a free gauge it hit its
evaluation limit without converging (measured on 2 views). On llff_like 12
views, in otherwise near-identical runs, it reached 0.094 deg median rotation
error and LM 0.012 deg (inexact LSMR steps stop short of the optimum).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from mvgeo.align.bundle_lm import (
    LMProblem,
    camera_centre_std,
    log_focal_std,
    principal_std,
    project,
    solve_lm_principal,
)
from mvgeo.triangulate import TriangulationCriteria, triangulate_multiview

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BundleConfig:
    """Options of `bundle_adjust`.

    Attributes:
        huber_px: Huber loss scale (pixels).
        max_nfev: function evaluations of `least_squares`.
        shared_focal: one focal for all views.
        optimize_focal: False keeps the focals fixed (known intrinsics).
        max_points: at most this many tracks (evenly subsampled) enter the problem.
        max_reproj_px: observations above this after the first solve are removed.
        min_track_length: tracks need at least this many views.
        solver: "lm" (`mvgeo.align.bundle_lm`: Levenberg-Marquardt with the
            Schur complement, analytic Jacobian) or "scipy" (`least_squares`
            with a sparse finite-difference Jacobian: the slow reference).
        max_iters: LM iterations per round ("lm" only).
        rel_tol: LM stops when a step lowers the cost by less than this fraction. The last
            iterations of an IRLS Huber adjustment lower the cost linearly, by 1e-5 to 1e-6 each
            (DTU scan24: 10 of its 20 iterations); stopping at 1e-5 instead of 1e-6 moved the
            median rotation error by at most 0.0005 deg on DTU scan24 (clean and noisy), the temple
            ring, llff_like (3, 6 and 12 views) and object_ring, and took 1-6 % off `mvgeo align`'s
            time (1e-6 against 1e-10 on llff_like: < 0.01 % of the error, half the time).
        refine_principal: the principal point, one for all views, is an unknown of the LM solver (False: fixed
            at the image centre, as COLMAP's default); `BundleResult.principal_px` and `principal_std_px` give
            it. The alignment estimates it for its accepted result and keeps it only where the views determine
            it (`mvgeo.align.principal`; docs/bench/principal_point.md).
        readjust_min_gain: adjust once more when the adjusted poses triangulate at least this fraction
            more tracks than the start did (`bundle_adjust`); 0 never. 5 %: on the real benchmark sets the
            final candidates gain 0-3 % (temple 1889 -> 1889, DTU scan24 905 -> 905, 775 -> 781), starts a
            degree off gain 7-22 %.
    """

    huber_px: float = 1.0
    max_nfev: int = 200
    shared_focal: bool = True
    optimize_focal: bool = True
    max_points: int = 20000
    max_reproj_px: float = 4.0
    min_track_length: int = 2
    solver: str = "lm"
    max_iters: int = 20
    rel_tol: float = 1e-5
    readjust_min_gain: float = 0.05
    refine_principal: bool = False


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
    focal_log_std: float = float("nan")
    #: (N,) largest standard deviation of each camera centre, world units (`bundle_lm.camera_centre_std`;
    #: LM solver only).
    centre_std: np.ndarray | None = None
    solver: str = "lm"
    #: (2,) the principal point (pixels at `size_wh`) the poses go with: the image centre unless
    #: `BundleConfig.refine_principal`, then the refined one, with its standard deviation (`principal_std_px`).
    principal_px: np.ndarray | None = None
    principal_std_px: np.ndarray | None = None
    #: The refined tracks, for what has to agree with the new poses (e.g. the dense depth maps):
    #: (P, 3) world points and per observation its view, point index and (u, v) pixel.
    track_xyz: np.ndarray | None = None
    obs_view: np.ndarray | None = None
    obs_point: np.ndarray | None = None
    obs_uv: np.ndarray | None = None
    #: The adjustment ran a second time on the tracks its first result triangulated (`bundle_adjust`).
    readjusted: bool = False


def build_tracks(matches: Sequence[tuple[int, int, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge pairwise matches into tracks (connected components of the keypoint graph).

    A keypoint is a distinct (view, u, v); every match is an edge. The keypoints
    are numbered in order of first appearance, and the components are found by
    `scipy.sparse.csgraph.connected_components`; tracks are ordered by their
    first-seen keypoint and their observations by first appearance, exactly as
    the union-find reference `build_tracks_reference` orders them.

    Args:
        matches: (i, j, uv) with uv (M, 4) = (u_i, v_i, u_j, v_j).

    Returns:
        obs_view (K,), obs_track (K,), obs_uv (K, 2): one row per observation;
        tracks with two observations in one view are dropped; ids are 0..T-1.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    rows = [np.asarray(uv, np.float64).reshape(-1, 4) for _, _, uv in matches]
    if not rows or sum(len(r) for r in rows) == 0:
        return empty
    # Endpoints in the reference's visiting order: per match row, first the i side, then the j side.
    ends = np.concatenate([np.stack([np.stack([np.full(len(r), i, np.float64), r[:, 0], r[:, 1]], 1),
                                     np.stack([np.full(len(r), j, np.float64), r[:, 2], r[:, 3]], 1)], 1)
                           for (i, j, _), r in zip(matches, rows, strict=True)]).reshape(-1, 3)
    # Distinct keypoints (a stable lexicographic sort: each run of equal rows starts at its first appearance).
    srt = np.lexsort((ends[:, 2], ends[:, 1], ends[:, 0]))
    e = ends[srt]
    starts = np.r_[True, np.any(e[1:] != e[:-1], axis=1)]
    group = np.cumsum(starts) - 1  # sorted-distinct index of every sorted endpoint
    first = srt[starts]  # first appearance of each distinct keypoint
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    node = np.empty(len(ends), np.int64)
    node[srt] = rank[group]  # keypoint ids in order of first appearance
    keys = ends[np.sort(first)]  # (V, 3) view, u, v by id
    edges = node.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])), shape=(len(keys), len(keys)))
    _, comp = connected_components(graph, directed=False)
    # Component order: by its first keypoint; members by id.
    comp_first = np.full(comp.max() + 1, len(keys), np.int64)
    np.minimum.at(comp_first, comp, np.arange(len(keys)))
    order = np.lexsort((np.arange(len(keys)), comp_first[comp]))
    view = keys[:, 0].astype(np.int64)
    track_of = comp[order]
    # Drop tracks with two keypoints in one view.
    n_view = int(view.max()) + 1
    comp_view = np.unique(comp * n_view + view)
    n_views_per = np.bincount(comp_view // n_view, minlength=len(comp_first))
    size = np.bincount(comp, minlength=len(comp_first))
    ok_comp = n_views_per == size
    keep = ok_comp[track_of]
    order, track_of = order[keep], track_of[keep]
    ids = -np.ones(len(comp_first), np.int64)
    kept_in_order = track_of[np.r_[True, track_of[1:] != track_of[:-1]]] if len(track_of) else track_of
    ids[kept_in_order] = np.arange(len(kept_in_order))
    return view[order], ids[track_of], keys[order, 1:].copy()


def build_tracks_reference(matches: Sequence[tuple[int, int, np.ndarray]]
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Union-find on (view, u, v) keys, one match at a time: the slow, obvious reference of `build_tracks`."""
    parent: dict[tuple, tuple] = {}

    def find(a):
        root = a
        while parent[root] != root:
            root = parent[root]
        while parent[a] != root:
            parent[a], a = root, parent[a]
        return root

    for i, j, uv in matches:
        for row in uv:
            a, b = (i, float(row[0]), float(row[1])), (j, float(row[2]), float(row[3]))
            parent.setdefault(a, a)
            parent.setdefault(b, b)
            ra, rb = find(a), find(b)
            if ra != rb:
                parent[ra] = rb
    groups: dict[tuple, list[tuple]] = {}
    for key in parent:
        groups.setdefault(find(key), []).append(key)
    views, tracks, uvs = [], [], []
    tid = 0
    for members in groups.values():
        vs = [m[0] for m in members]
        if len(set(vs)) != len(vs):
            continue
        for m in members:
            views.append(m[0])
            tracks.append(tid)
            uvs.append(m[1:])
        tid += 1
    return np.array(views, np.int64), np.array(tracks, np.int64), np.array(uvs, np.float64).reshape(-1, 2)


def bundle_adjust(cam_from_world: np.ndarray, focal_px: np.ndarray, size_wh: tuple[int, int],
                  matches: Sequence[tuple[int, int, np.ndarray]], *, config: BundleConfig = BundleConfig()
                  ) -> BundleResult:
    """Refine poses and focals on feature tracks built from pairwise matches.

    The tracks are triangulated from the given poses; a track whose triangulation fails there (too little
    parallax, rays more than 3 deg apart: a start a degree off rejects good tracks) does not enter. When the
    tracks triangulated again from the adjusted poses are at least `BundleConfig.readjust_min_gain` more,
    the adjustment runs once more from its own result on them (COLMAP re-triangulates after each
    adjustment for the same reason). Measured on llff_like, 6 views at 256x192: starts that differed by a
    RANSAC outcome kept 369 or 419 tracks and ended 0.42 or 0.08 deg off; re-adjusted, 415-431 tracks and
    0.07-0.09 deg.

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
    ov, ot, ouv = build_tracks(matches)
    n_tracks = int(ot.max()) + 1 if len(ot) else 0
    length = np.bincount(ot, minlength=n_tracks)
    keep_track = length >= config.min_track_length
    stride = max(1, int(np.ceil(keep_track.sum() / config.max_points)))
    keep_track &= (np.cumsum(keep_track) % stride) == 0
    ids = np.flatnonzero(keep_track)
    remap = -np.ones(n_tracks, np.int64)
    remap[ids] = np.arange(len(ids))
    sel = keep_track[ot]
    tracks = (ov[sel], remap[ot[sel]], ouv[sel], len(ids))
    first = _triangulated(cam_from_world, focal_px, c, n, tracks)
    res = _adjust(cam_from_world, focal_px, c, n, first, config)
    if config.readjust_min_gain > 0 and res.n_points >= 10:
        # the tracks as the adjusted poses (and, when refined, principal point) triangulate them
        c2 = res.principal_px if config.refine_principal and res.principal_px is not None else c
        again = _triangulated(res.cam_from_world, res.focal_px, c2, n, tracks)
        if len(again[3]) >= (1.0 + config.readjust_min_gain) * len(first[3]):
            _log.info("bundle adjustment again: %d tracks triangulate from the adjusted poses, %d from the start",
                      len(again[3]), len(first[3]))
            res2 = _adjust(res.cam_from_world, res.focal_px, c2, n, again, config)
            res = replace(res2, reproj_rms_before_px=res.reproj_rms_before_px,
                          reproj_median_before_px=res.reproj_median_before_px, readjusted=True)
    return res


def _triangulated(cam_from_world, focal_px, c, n, tracks):
    """Multi-view triangulation of the tracks from the given poses: the valid tracks' observations
    (view, point, uv) renumbered, and their points."""
    ov, ot, ouv, n_ids = tracks
    rays = np.zeros((n, n_ids, 3))
    observed = np.zeros((n, n_ids), bool)
    rays[ov, ot, :2] = (ouv - c) / np.asarray(focal_px)[ov, None]
    rays[ov, ot, 2] = 1.0
    observed[ov, ot] = True
    crit = TriangulationCriteria(min_angle_deg=1.0, max_angular_error_deg=3.0)
    tri = triangulate_multiview(rays, cam_from_world, observed=observed, criteria=crit)
    good = tri.valid
    sel = good[ot]
    remap = -np.ones(n_ids, np.int64)
    remap[good] = np.arange(good.sum())
    return ov[sel], remap[ot[sel]], ouv[sel], tri.points[good]


def _adjust(cam_from_world, focal_px, c, n, observations, config: BundleConfig) -> BundleResult:
    """One adjustment (LM or the scipy reference) of the poses, focal(s) and triangulated tracks."""
    ov, op, ouv, X0 = observations
    P = len(X0)
    nf = 1 if config.shared_focal else n
    f_index = np.zeros(n, np.int64) if config.shared_focal else np.arange(n)
    logf0 = np.array([np.mean(np.log(focal_px))]) if config.shared_focal else np.log(focal_px)
    rv0 = Rotation.from_matrix(cam_from_world[:, :, :3]).as_rotvec()
    fixed = (rv0[0].copy(), cam_from_world[0, :, 3].copy(), np.log(_baseline(rv0, cam_from_world[:, :, 3])))
    x0 = np.concatenate([rv0[1:].reshape(-1), cam_from_world[1:, :, 3].reshape(-1)]
                        + ([logf0] if config.optimize_focal else []) + [X0.reshape(-1)])
    e0 = _errors(x0, n, nf, P, ov, op, ouv, f_index, logf0, c, config, fixed)
    if P < 10:
        _log.warning("bundle adjustment skipped: only %d triangulated tracks", P)
        rms = float(np.sqrt(np.mean(e0**2))) if len(e0) else float("nan")
        med = float(np.median(e0)) if len(e0) else float("nan")
        return BundleResult(cam_from_world.copy(), np.asarray(focal_px, float).copy(), P, len(ov), rms, rms, med, med)
    if config.solver == "lm":
        return _bundle_lm(cam_from_world, rv0, X0, logf0, f_index, ov, op, ouv, c, e0, config)
    if config.solver != "scipy":
        raise ValueError(f"unknown bundle solver {config.solver!r} (lm or scipy)")
    x = x0
    for _round in range(2):
        x = _solve(x, n, nf, P, ov, op, ouv, f_index, logf0, c, config, fixed)
        e = _errors(x, n, nf, P, ov, op, ouv, f_index, logf0, c, config, fixed)
        ok = e < config.max_reproj_px
        if ok.all() or _round == 1:
            break
        ov, op, ouv = ov[ok], op[ok], ouv[ok]
    e1 = _errors(x, n, nf, P, ov, op, ouv, f_index, logf0, c, config, fixed)
    rv, t, lf, Xw = _unpack(x, n, nf, P, logf0, config, fixed)
    out = np.concatenate([Rotation.from_rotvec(rv).as_matrix(), t[:, :, None]], axis=2)
    res = BundleResult(out, np.exp(lf)[f_index], P, len(ov), float(np.sqrt(np.mean(e0**2))),
                       float(np.sqrt(np.mean(e1**2))), float(np.median(e0)), float(np.median(e1)), solver="scipy",
                       track_xyz=np.asarray(Xw).reshape(-1, 3), obs_view=ov, obs_point=op, obs_uv=ouv)
    _log.info("bundle adjustment: %d tracks, %d observations, reprojection RMS %.3g -> %.3g px "
              "(median %.3g -> %.3g)", P, len(ov), res.reproj_rms_before_px, res.reproj_rms_after_px,
              res.reproj_median_before_px, res.reproj_median_after_px)
    return res


def _bundle_lm(cam_from_world, rv0, X0, logf0, f_index, ov, op, ouv, c, e0, config) -> BundleResult:
    R = Rotation.from_rotvec(rv0).as_matrix()
    t = cam_from_world[:, :, 3].copy()
    logf, X = logf0.copy(), X0.copy()
    pb = LMProblem(ov, op, ouv, f_index, c, config.optimize_focal, config.refine_principal)
    for _round in range(2):  # solve, drop observations above max_reproj_px, solve again
        R, t, logf, X, c, _ = solve_lm_principal(R, t, logf, X, pb, huber_px=config.huber_px,
                                                 max_iters=config.max_iters, tol=config.rel_tol)
        pb = pb.with_principal(c)
        e = np.linalg.norm(project(R, t, logf, X, pb)[0], axis=1)
        ok = e < config.max_reproj_px
        if ok.all() or _round == 1:
            break
        # Keep points that still have two observations; renumber them.
        ok &= np.bincount(pb.op[ok], minlength=len(X))[pb.op] >= 2
        keep_pt = np.bincount(pb.op[ok], minlength=len(X)) >= 2
        ok &= keep_pt[pb.op]
        new_id = np.cumsum(keep_pt) - 1
        X = X[keep_pt]
        pb = LMProblem(pb.ov[ok], new_id[pb.op[ok]], pb.uv[ok], f_index, c, config.optimize_focal,
                       config.refine_principal)
    e1 = np.linalg.norm(project(R, t, logf, X, pb)[0], axis=1)
    std = log_focal_std(R, t, logf, X, pb, config.huber_px)
    centre_std = camera_centre_std(R, t, logf, X, pb, config.huber_px)
    out = np.concatenate([R, t[:, :, None]], axis=2)
    res = BundleResult(out, np.exp(logf)[f_index], len(X), len(pb.ov), float(np.sqrt(np.mean(e0**2))),
                       float(np.sqrt(np.mean(e1**2))), float(np.median(e0)), float(np.median(e1)),
                       focal_log_std=float(np.max(std)) if len(std) else 0.0, centre_std=centre_std, solver="lm",
                       principal_px=np.asarray(c, np.float64).copy(),
                       principal_std_px=principal_std(R, t, logf, X, pb, config.huber_px),
                       track_xyz=X, obs_view=pb.ov, obs_point=pb.op, obs_uv=pb.uv)
    _log.info("bundle adjustment (LM): %d tracks, %d observations, reprojection RMS %.3g -> %.3g px "
              "(median %.3g -> %.3g), focal %.1f -> %.1f px (log-std %.2g)", len(X), len(pb.ov),
              res.reproj_rms_before_px, res.reproj_rms_after_px, res.reproj_median_before_px,
              res.reproj_median_after_px, float(np.exp(np.median(logf0))), float(np.median(res.focal_px)),
              res.focal_log_std)
    return res


def _unpack(x, n, nf, P, logf0, config, fixed):
    k = n - 1  # view 0's pose is fixed
    rv = np.concatenate([fixed[0][None], x[:3 * k].reshape(k, 3)])
    t = np.concatenate([fixed[1][None], x[3 * k:6 * k].reshape(k, 3)])
    if config.optimize_focal:
        lf, rest = x[6 * k:6 * k + nf], x[6 * k + nf:]
    else:
        lf, rest = logf0, x[6 * k:]
    return rv, t, lf, rest.reshape(P, 3)


def _errors(*args) -> np.ndarray:
    """(K,) reprojection error norms in pixels."""
    return np.linalg.norm(_residuals(*args)[:-1].reshape(-1, 2), axis=1)


def _residuals(x, n, nf, P, ov, op, ouv, f_index, logf0, c, config, fixed):
    rv, t, lf, Xw = _unpack(x, n, nf, P, logf0, config, fixed)
    R = Rotation.from_rotvec(rv).as_matrix()[ov]
    xc = np.einsum("mij,mj->mi", R, Xw[op]) + t[ov]
    f = np.exp(lf)[f_index[ov]]
    z = np.where(np.abs(xc[:, 2]) < 1e-9, 1e-9, xc[:, 2])
    proj = f[:, None] * xc[:, :2] / z[:, None] + c
    gauge = _GAUGE_WEIGHT * (np.log(_baseline(rv, t)) - fixed[2])
    return np.concatenate([(proj - ouv).reshape(-1), [gauge]])


#: Weight of the scale-gauge residual (log baseline), in pixel-equivalents.
_GAUGE_WEIGHT = 100.0


def _baseline(rv: np.ndarray, t: np.ndarray) -> float:
    R = Rotation.from_rotvec(rv[:2]).as_matrix()
    c0, c1 = -R[0].T @ t[0], -R[1].T @ t[1]
    return float(np.linalg.norm(c1 - c0)) + 1e-300


def _solve(x0, n, nf, P, ov, op, ouv, f_index, logf0, c, config, fixed):
    # Jacobian sparsity: each residual pair depends on its view's pose (none for view 0), focal and point.
    m = len(ov)
    k = n - 1
    pt0 = 6 * k + (nf if config.optimize_focal else 0)
    obs_rows, obs_cols = [], []
    free = ov > 0
    for d in range(3):
        obs_rows += [np.flatnonzero(free)] * 2
        obs_cols += [3 * (ov[free] - 1) + d, 3 * k + 3 * (ov[free] - 1) + d]
        obs_rows.append(np.arange(m))
        obs_cols.append(pt0 + 3 * op + d)
    if config.optimize_focal:
        obs_rows.append(np.arange(m))
        obs_cols.append(6 * k + f_index[ov])
    r = np.concatenate(obs_rows)
    cidx = np.concatenate(obs_cols)
    gauge_cols = np.array([0, 1, 2, 3 * k, 3 * k + 1, 3 * k + 2])  # view 1's rotation and translation
    rows = np.concatenate([2 * r, 2 * r + 1, np.full(6, 2 * m)])
    cols = np.concatenate([cidx, cidx, gauge_cols])
    S = coo_matrix((np.ones(len(cols), np.int8), (rows, cols)), shape=(2 * m + 1, len(x0))).tocsr()
    sol = least_squares(_residuals, x0, jac_sparsity=S, loss="huber", f_scale=config.huber_px,
                        max_nfev=config.max_nfev, x_scale="jac", method="trf", tr_solver="lsmr",
                        args=(n, nf, P, ov, op, ouv, f_index, logf0, c, config, fixed))
    return sol.x
