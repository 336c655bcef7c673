"""Global positioning: camera centres and track points from known rotations (GLOMAP's translation stage).

With the rotations fixed (e.g. by `rotation_averaging`), every observation of track p in view n gives the
world-frame unit ray ``v = normalize(R_n^T K_n^-1 [u, v, 1])`` (pixels in our convention, docs/conventions.md),
which must point from the centre C_n towards the point X_p. The unknowns are the centres C (N, 3), the points
X (P, 3) and one scale d >= `_MIN_SCALE` per observation; the residual of an observation is the 3-vector

    r = v - d (X_p - C_n)

(BATA, Zhuang et al. 2018; GLOMAP's point-to-camera constraints, Pan et al. 2024). For a fixed direction the
best d gives ``|r| = sin(angle(v, X_p - C_n))`` when the point is in front of the camera and ``|r| = 1``
behind it: the residual is an angle whatever the point's distance, so distant points count as much as near
ones, and it is bounded, so a wrong match costs at most 1.

- Loss: Cauchy (default) or Huber on ``|r|`` with scale `GlobalPositioningConfig.loss_scale` (the sine of an
  angle: 0.05 is about 2.9 deg), minimised by iteratively reweighted Levenberg-Marquardt. On synthetic
  rings and forward-facing rows with 10 % wrong observations (no second round), Cauchy's vanishing pull of
  far residuals gave 1.7-2.9x smaller centre errors than Huber's constant one, in fewer iterations.
- Gauge: the data residuals do not change under ``(C, X, d) -> (s C + t, s X + t, d / s)``. Four extra
  residuals ``sqrt(K) * mean(C)`` (3) and ``sqrt(K) * (mean |C - mean(C)|^2 - 1)`` fix it: the centroid of the
  centres at the origin and their RMS distance from it at 1. Every solution can be moved onto that slice,
  so these residuals are zero at the optimum and do not bias it; they make the normal equations full rank.
- Start: the LUD solution (`mvgeo.align.lud.lud_positions`), which cannot collapse and resists wrong
  matches; "random" starts from uniform positions in [-1, 1]^3 (seeded) as GLOMAP does, and needs many more
  iterations.
- Two rounds: after the first solve, observations behind their camera or more than `max_residual_deg` off
  their ray are dropped (then tracks with fewer than 2 views), and the problem is solved again from there.
- The linear system: the scales are eliminated in closed form (each touches one residual), then the points
  (3 x 3 blocks), leaving a dense (3N, 3N) system over the centres. Scales on their bound that the gradient
  pushes down stay fixed in that step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix, diags

from mvgeo.align.bundle import build_tracks
from mvgeo.align.graph import components
from mvgeo.align.lud import lud_positions
from mvgeo.common.errors import DegenerateGeometryError, InputError, check_shape

#: Lower bound of the scales d (GLOMAP bounds them the same way); the centres have RMS radius 1.
_MIN_SCALE = 1e-5
#: Damped solves per LM iteration before the iteration counts as converged. A rejected step raises the
#: damping to at least 1e-4 and then 4x per try, so the last try damps by at least 1e-4 * 4^13 ~ 7e3 times
#: H's diagonal: no step down to that length lowers the cost. Growing it from where it stood until 1e16
#: instead took 18 solves (0.1 s) on the temple ring's converged second round.
_MAX_TRIES = 14

__all__ = ["GlobalPositioningConfig", "GlobalPositioningResult", "global_positions", "observation_rays"]


@dataclass(frozen=True)
class GlobalPositioningConfig:
    """Options of `global_positions`.

    Attributes:
        loss: "huber", "cauchy" or "trivial" (plain least squares), on the residual norm |r|.
        loss_scale: |r| (about the sine of the ray angle) where the loss stops being quadratic.
        max_iters: LM iterations per round at most.
        rel_tol: a round stops when an accepted step lowers the cost by less than this fraction. The
            positions start the global alignment and the bundle adjustment, which refine them: on noisy DTU
            scan24 the first round's last 11 of 40 iterations at 1e-10 each lowered the cost by less than
            1e-6, and stopping there (1e-6) left the adjusted poses within 0.001 deg.
        max_residual_deg: after the first round, observations further than this from their ray are dropped.
        min_track_length: tracks need at least this many views.
        min_parallax_ratio: the solution is refused as collapsed (pure rotation) unless the median angle of
            the observations to their track's mean ray (what the rotations alone explain) is at least this
            many times the median residual angle of the solution (a pure rotation leaves both at the noise
            level: about 1.4x apart for 2-view tracks; a real baseline leaves parallax/noise, tens or more).
        init: "lud" (`mvgeo.align.lud.lud_positions`) or "random" (uniform in [-1, 1]^3, seeded).
        init_iterations: reweighting iterations of the LUD start.
        seed: of the random start.
    """

    loss: str = "cauchy"
    loss_scale: float = 0.05
    max_iters: int = 100
    rel_tol: float = 1e-6
    max_residual_deg: float = 5.0
    min_track_length: int = 2
    min_parallax_ratio: float = 3.0
    init: str = "lud"
    init_iterations: int = 50
    seed: int = 0


@dataclass(frozen=True)
class GlobalPositioningResult:
    """Camera centres and points in the gauge of the module docstring (centroid 0, centre RMS radius 1).

    Attributes:
        cam_from_world: (N, 3, 4) ``[R | -R C]`` with the input rotations.
        points_xyz: (P, 3) world points of the tracks that were used.
        track_ids: (P,) their ids in `bundle.build_tracks(matches)` numbering.
        obs_view, obs_point, obs_uv: (K,), (K,), (K, 2): the observations used (view, row of `points_xyz`, pixel).
        n_obs_per_view: (N,) observations used per view.
        final_cost: ``0.5 * sum(loss(|r|^2))`` over the used observations (gauge residuals excluded).
        iterations: LM iterations over both rounds.
        converged: both rounds stopped on `rel_tol` before `max_iters`.
    """

    cam_from_world: np.ndarray
    points_xyz: np.ndarray
    track_ids: np.ndarray
    obs_view: np.ndarray
    obs_point: np.ndarray
    obs_uv: np.ndarray
    n_obs_per_view: np.ndarray
    final_cost: float
    iterations: int
    converged: bool


def observation_rays(R_cam_from_world: np.ndarray, K: np.ndarray, obs_view: np.ndarray,
                     obs_uv: np.ndarray) -> np.ndarray:
    """(K, 3) unit world-frame rays ``normalize(R_n^T K_n^-1 [u, v, 1])`` of pixels (K, 2) seen in views (K,)."""
    h = np.concatenate([obs_uv, np.ones((len(obs_uv), 1))], axis=1)
    ray_cam = np.einsum("kij,kj->ki", np.linalg.inv(K)[obs_view], h)
    ray_world = np.einsum("kji,kj->ki", R_cam_from_world[obs_view], ray_cam)  # R^T ray
    return ray_world / np.linalg.norm(ray_world, axis=1, keepdims=True)


def _loss(s2: np.ndarray, kind: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """rho(s^2) and its derivative (the IRLS weight) for squared residual norms s2."""
    if kind == "trivial":
        return s2, np.ones_like(s2)
    if kind == "huber":
        s = np.sqrt(s2)
        outer = s > scale
        return (np.where(outer, 2.0 * scale * s - scale**2, s2),
                np.where(outer, scale / np.maximum(s, 1e-300), 1.0))
    if kind == "cauchy":
        return scale**2 * np.log1p(s2 / scale**2), 1.0 / (1.0 + s2 / scale**2)
    raise InputError(f"unknown loss {kind!r}", fix="use 'huber', 'cauchy' or 'trivial'")


class _Problem:
    """Residuals and Jacobian of the module docstring's problem; unknowns z = [C (3N), X (3P), d (K)]."""

    def __init__(self, rays: np.ndarray, obs_view: np.ndarray, obs_point: np.ndarray, n_views: int,
                 n_points: int):
        self.v, self.ov, self.op = rays, obs_view, obs_point
        self.n, self.p, self.k = n_views, n_points, len(rays)
        self.gauge_w = np.sqrt(max(self.k, 1))

    def split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n3, p3 = 3 * self.n, 3 * self.p
        return z[:n3].reshape(-1, 3), z[n3:n3 + p3].reshape(-1, 3), z[n3 + p3:]

    def residuals(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Data residuals (K, 3) and gauge residuals (4,)."""
        C, X, d = self.split(z)
        r = self.v - d[:, None] * (X[self.op] - C[self.ov])
        Cc = C - C.mean(axis=0)
        g = self.gauge_w * np.r_[C.mean(axis=0), np.mean(np.sum(Cc * Cc, axis=1)) - 1.0]
        return r, g

    def jacobian(self, z: np.ndarray):
        """Sparse (3K + 4, 3N + 3P + K) Jacobian of [data residuals (row-major), gauge residuals]."""
        C, X, d = self.split(z)
        n, p, k = self.n, self.p, self.k
        w = X[self.op] - C[self.ov]
        rows3 = 3 * np.arange(k)[:, None] + np.arange(3)
        Cc = C - C.mean(axis=0)
        rows = np.concatenate([rows3.ravel(), rows3.ravel(), rows3.ravel(),
                               np.repeat(3 * k + np.arange(3), n), np.full(3 * n, 3 * k + 3)])
        cols = np.concatenate([(3 * self.ov[:, None] + np.arange(3)).ravel(),
                               (3 * n + 3 * self.op[:, None] + np.arange(3)).ravel(),
                               np.repeat(3 * n + 3 * p + np.arange(k), 3),
                               (3 * np.arange(n)[None, :] + np.arange(3)[:, None]).ravel(),
                               np.arange(3 * n)])
        vals = np.concatenate([np.repeat(d, 3), -np.repeat(d, 3), (-w).ravel(),
                               np.full(3 * n, self.gauge_w / n), (self.gauge_w * 2.0 / n * Cc).ravel()])
        return coo_matrix((vals, (rows, cols)), shape=(3 * k + 4, 3 * n + 3 * p + k)).tocsr()

    def cost(self, z: np.ndarray, config: GlobalPositioningConfig) -> tuple[float, float]:
        """(data cost 0.5 * sum rho(|r|^2), gauge cost 0.5 * |g|^2)."""
        r, g = self.residuals(z)
        rho, _ = _loss(np.sum(r * r, axis=1), config.loss, config.loss_scale)
        return 0.5 * float(rho.sum()), 0.5 * float(g @ g)


def _solve_eliminating_points(S, rhs: np.ndarray, n_cam: int) -> np.ndarray:
    """Solve ``S x = rhs`` for x = [C (n_cam), X (3P)] when the X-X block of S is block diagonal (3 x 3).

    Each point's unknowns meet only that point's residuals, so its block is inverted on its own and the
    points are eliminated (Schur complement), leaving a dense (n_cam, n_cam) system over the centres.
    """
    S_xx = S[n_cam:, n_cam:].tocoo()
    blocks = np.zeros(((S.shape[0] - n_cam) // 3, 3, 3))
    np.add.at(blocks, (S_xx.row // 3, S_xx.row % 3, S_xx.col % 3), S_xx.data)
    inv = np.linalg.inv(blocks)
    p, r, c = np.indices(inv.shape).reshape(3, -1)
    inv_xx = coo_matrix((inv.ravel(), (3 * p + r, 3 * p + c)), shape=(3 * len(inv), 3 * len(inv))).tocsr()
    S_cx = S[:n_cam, n_cam:]
    T = S_cx @ inv_xx
    d_cam = np.linalg.solve(S[:n_cam, :n_cam].toarray() - (T @ S_cx.T).toarray(), rhs[:n_cam] - T @ rhs[n_cam:])
    return np.r_[d_cam, inv_xx @ (rhs[n_cam:] - S_cx.T @ d_cam)]


class _Normal:
    """The IRLS-weighted normal equations ``H step = b`` at one state, in blocks (`_damped_step` solves them).

    Per observation k (view n, point p, u = X_p - C_n, weight w, scale d) the residual ``v - d u`` has the
    Jacobian ``d I`` in C_n, ``-d I`` in X_p and ``-u`` in d_k, so H's point blocks are ``sum w d^2 I`` (a
    scalar times I), its centre-point blocks ``-sum w d^2 I``, its scale entries ``w |u|^2`` and the
    scale's coupling ``-w d u`` (centre) and ``w d u`` (point). The gauge residuals touch the centres only:
    they add a dense (3N, 3N) term. `_Problem.jacobian` is the sparse Jacobian these blocks are checked
    against (tests).
    """

    def __init__(self, problem: _Problem, z: np.ndarray, wt: np.ndarray):
        C, X, d = problem.split(z)
        n, ov, op = problem.n, problem.ov, problem.op
        self.u = X[op] - C[ov]
        r = problem.v - d[:, None] * self.u
        Cc = C - C.mean(axis=0)
        gw = problem.gauge_w
        g = gw * np.r_[C.mean(axis=0), np.mean(np.sum(Cc * Cc, axis=1)) - 1.0]
        Jg = np.zeros((4, 3 * n))
        Jg[np.repeat(np.arange(3), n), (3 * np.arange(n)[None, :] + np.arange(3)[:, None]).ravel()] = gw / n
        Jg[3] = gw * 2.0 / n * Cc.ravel()
        self.wd = wt * d  # (K,)
        self.wd2 = self.wd * d
        self.h_cc = Jg.T @ Jg  # (3N, 3N) gauge term; the data add w d^2 I per view
        self.cc_diag = np.bincount(ov, self.wd2, minlength=n)
        self.xx = np.bincount(op, self.wd2, minlength=problem.p)  # (P,) point blocks xx[p] * I
        self.dd = wt * np.sum(self.u * self.u, axis=1)  # (K,)
        wdr = self.wd[:, None] * r
        self.b_c = -(np.stack([np.bincount(ov, wdr[:, a], minlength=n) for a in range(3)], axis=1).ravel()
                     + Jg.T @ g)
        self.b_x = np.stack([np.bincount(op, wdr[:, a], minlength=problem.p) for a in range(3)], axis=1)
        self.b_d = wt * np.sum(self.u * r, axis=1)
        self.problem = problem

    def diagonal(self) -> np.ndarray:
        """diag(H) in the unknowns' order [C (3N), X (3P), d (K)]."""
        return np.r_[np.diag(self.h_cc) + np.repeat(self.cc_diag, 3), np.repeat(self.xx, 3), self.dd]


def _block_sum(index: np.ndarray, blocks: np.ndarray, n_out: int) -> np.ndarray:
    """(n_out, 3, 3): the (K, 3, 3) `blocks` summed by `index` (K,) (`np.add.at`'s result, by `np.bincount`)."""
    flat = (index[:, None] * 9 + np.arange(9)).ravel()
    return np.bincount(flat, blocks.reshape(-1), minlength=9 * n_out).reshape(n_out, 3, 3)


def _block_matrix(ov: np.ndarray, op: np.ndarray, blocks: np.ndarray, n: int, p: int) -> csr_matrix:
    """Sparse (3n, 3p) matrix with the (K, 3, 3) `blocks` at block positions (ov[k], op[k]) (duplicates summed)."""
    rows = (3 * ov[:, None, None] + np.arange(3)[None, :, None]) + np.zeros((1, 1, 3), np.int64)
    cols = (3 * op[:, None, None] + np.arange(3)[None, None, :]) + np.zeros((1, 3, 1), np.int64)
    return csr_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * p))


def _damped_step(nq: _Normal, lam: float, D: np.ndarray, free: np.ndarray) -> np.ndarray:
    """The step of ``(H + lam diag(D)) step = b``: the scales eliminated (1 x 1 each; fixed ones, `free`
    False, held), then the points (3 x 3 each), then a dense (3N, 3N) solve; `_damped_step_sparse` is the
    same solve on the sparse matrices. The points' Schur term ``sum_p B_p V_p^-1 B_p^T`` is one product of
    two sparse (3N, 3P) block matrices (a block per observation), so the work grows with the observations
    and their pairs within tracks, not with views x points."""
    pb = nq.problem
    n, P, ov, op = pb.n, pb.p, pb.ov, pb.op
    m3n = 3 * n
    Dc, Dx, Dd = D[:m3n], D[m3n:m3n + 3 * P].reshape(P, 3), D[m3n + 3 * P:]
    a = np.where(free, 1.0 / (nq.dd + lam * Dd), 0.0)  # (K,) inverse of each scale's damped entry
    q = a * nq.wd * nq.wd  # the coupling's outer products u u^T enter with this factor
    quu = q[:, None, None] * (nq.u[:, :, None] * nq.u[:, None, :])  # (K, 3, 3)
    eye = np.eye(3)
    # Each observation's centre-point block (symmetric): -w d^2 I + q u u^T in rows C_n, columns X_p.
    B = -nq.wd2[:, None, None] * eye + quu
    # Centre blocks (dense, with the gauge term) and point blocks, scales eliminated.
    S = nq.h_cc + np.diag(lam * Dc)
    blk = _block_sum(ov, -B, n)
    idx = 3 * np.arange(n)[:, None] + np.arange(3)
    S[idx[:, :, None], idx[:, None, :]] += blk
    V = nq.xx[:, None, None] * eye + lam * Dx[:, :, None] * eye - _block_sum(op, quu, P)  # damped, per point
    Vinv = np.linalg.inv(V)
    coup = (a * nq.b_d * nq.wd)[:, None] * nq.u  # (K, 3): the scales' right-hand side carried over
    rhs_c = nq.b_c + np.stack([np.bincount(ov, coup[:, k], minlength=n) for k in range(3)], axis=1).ravel()
    rhs_x = nq.b_x - np.stack([np.bincount(op, coup[:, k], minlength=P) for k in range(3)], axis=1)
    Y = B @ Vinv[op]  # (K, 3, 3)
    S -= (_block_matrix(ov, op, Y, n, P) @ _block_matrix(ov, op, B, n, P).T).toarray()
    yr = np.einsum("kij,kj->ki", Y, rhs_x[op])
    rhs = rhs_c - np.stack([np.bincount(ov, yr[:, k], minlength=n) for k in range(3)], axis=1).ravel()
    dC = np.linalg.solve(S, rhs)
    bc = np.einsum("kij,kj->ki", B, dC.reshape(n, 3)[ov])  # B symmetric: B^T dC_n
    sum_bc = np.stack([np.bincount(op, bc[:, k], minlength=P) for k in range(3)], axis=1)
    dX = np.einsum("pij,pj->pi", Vinv, rhs_x - sum_bc)
    dd = a * (nq.b_d - nq.wd * np.sum(nq.u * (dX[op] - dC.reshape(n, 3)[ov]), axis=1))
    return np.r_[dC, dX.ravel(), dd]


def _damped_step_sparse(problem: _Problem, z: np.ndarray, wt: np.ndarray, lam: float, free: np.ndarray
                        ) -> np.ndarray:
    """`_damped_step` from the sparse Jacobian (`_Problem.jacobian`): the slow, obvious reference."""
    m = 3 * problem.n + 3 * problem.p
    r, g = problem.residuals(z)
    sw = np.r_[np.repeat(np.sqrt(wt), 3), np.ones(4)]
    J = diags(sw) @ problem.jacobian(z)
    f = sw * np.r_[r.ravel(), g]
    H = (J.T @ J).tocsr()
    b = -(J.T @ f)
    D = np.clip(H.diagonal(), 1e-12, 1e32)
    A = H + diags(lam * D)
    A_zz, A_zs = A[:m, :m], A[:m, m:]
    inv_ss = np.where(free, 1.0 / A[m:, m:].diagonal(), 0.0)
    S = (A_zz - A_zs @ diags(inv_ss) @ A_zs.T).tocsr()
    dz = _solve_eliminating_points(S, b[:m] - A_zs @ (b[m:] * inv_ss), 3 * problem.n)
    return np.r_[dz, (b[m:] - A_zs.T @ dz) * inv_ss]


def _lm(problem: _Problem, z: np.ndarray, config: GlobalPositioningConfig) -> tuple[np.ndarray, int, bool]:
    """Iteratively reweighted Levenberg-Marquardt (Marquardt's diagonal damping); returns z, iterations, converged."""
    m = 3 * problem.n + 3 * problem.p  # unknowns kept after eliminating the K scales
    cost = sum(problem.cost(z, config))
    lam = 1e-4
    iterations, converged = 0, False
    while iterations < config.max_iters:
        iterations += 1
        r, _ = problem.residuals(z)
        _, wt = _loss(np.sum(r * r, axis=1), config.loss, config.loss_scale)
        nq = _Normal(problem, z, wt)
        D = np.clip(nq.diagonal(), 1e-12, 1e32)
        # Scales on their lower bound that the gradient pushes further down stay fixed in this step.
        free = ~((z[m:] <= _MIN_SCALE * (1.0 + 1e-9)) & (nq.b_d <= 0.0))
        for _ in range(_MAX_TRIES):
            z_new = z + _damped_step(nq, lam, D, free)
            z_new[m:] = np.maximum(z_new[m:], _MIN_SCALE)
            new_cost = sum(problem.cost(z_new, config))
            if np.isfinite(new_cost) and new_cost < cost:
                z, decrease = z_new, (cost - new_cost) / max(cost, 1e-300)
                cost, lam = new_cost, max(lam / 3.0, 1e-12)
                break
            lam = max(lam * 4.0, 1e-4)
        else:  # no step lowers the cost, down to heavily damped ones: a minimum to working precision
            return z, iterations, True
        if decrease < config.rel_tol:
            converged = True
            break
    return z, iterations, converged


def _check_views(n_views: int, obs_view: np.ndarray, obs_point: np.ndarray, stage: str) -> None:
    counts = np.bincount(obs_view, minlength=n_views)
    if np.any(counts == 0):
        raise DegenerateGeometryError(f"global positioning ({stage}): views {np.flatnonzero(counts == 0).tolist()} "
                                      "have no usable observations in tracks of 2 or more views")
    first = np.full(int(obs_point.max()) + 1, -1)
    first[obs_point[::-1]] = obs_view[::-1]  # the first view of each track (the last write wins)
    pairs = np.stack([first[obs_point], obs_view], axis=1)
    comps = components(n_views, [tuple(e) for e in np.unique(pairs[pairs[:, 0] != pairs[:, 1]], axis=0).tolist()])
    if len(comps) > 1:
        raise DegenerateGeometryError(f"global positioning ({stage}): the views are not connected by tracks; "
                                      f"components {comps}")


def _keep_tracks(obs_view, obs_point, keep, min_len):
    """Apply an observation mask, then drop tracks with fewer than `min_len` views; renumber points 0..P-1."""
    n_pts = int(obs_point.max()) + 1 if len(obs_point) else 0
    length = np.bincount(obs_point[keep], minlength=n_pts)
    keep = keep & (length[obs_point] >= min_len)
    used = np.flatnonzero(length >= min_len)
    remap = -np.ones(n_pts, np.int64)
    remap[used] = np.arange(len(used))
    return keep, remap, used


def global_positions(R_cam_from_world: np.ndarray, K: np.ndarray, matches: Sequence[tuple[int, int, np.ndarray]],
                     config: GlobalPositioningConfig = GlobalPositioningConfig()) -> GlobalPositioningResult:
    """Camera centres and track points from fixed rotations and pairwise matches (module docstring).

    Args:
        R_cam_from_world: (N, 3, 3) rotations, held fixed.
        K: (N, 3, 3) intrinsics of the pixels in `matches` (our pixel convention).
        matches: (i, j, uv) with uv (M, 4) = (u_i, v_i, u_j, v_j), merged into tracks by `bundle.build_tracks`.
        config: options.

    Returns:
        `GlobalPositioningResult` (float64), in the gauge centroid 0, RMS centre radius 1.

    Raises:
        InputError: an unknown loss, a view index out of range or non-finite pixels.
        DegenerateGeometryError: a view has no usable observation, the views are not connected by tracks,
            or the solution collapses (the rotations alone explain the rays: no measurable baseline).
    """
    R = np.asarray(R_cam_from_world, np.float64)
    Kf = np.asarray(K, np.float64)
    check_shape(R, ["N", 3, 3], "R_cam_from_world")
    n = R.shape[0]
    check_shape(Kf, [n, 3, 3], "K")
    for i, j, uv in matches:
        if not (0 <= i < n and 0 <= j < n and i != j):
            raise InputError(f"global positioning: match pair ({i}, {j}) is not two distinct views of 0..{n - 1}")
        if not np.all(np.isfinite(np.asarray(uv, np.float64))):
            raise InputError(f"global positioning: non-finite pixel coordinates in the matches of pair ({i}, {j})")
    _loss(np.ones(1), config.loss, config.loss_scale)  # rejects an unknown loss before any work
    ov, ot, ouv = build_tracks(matches)
    keep, remap, used = _keep_tracks(ov, ot, np.ones(len(ov), bool), max(2, config.min_track_length))
    ov, op, ouv, track_ids = ov[keep], remap[ot[keep]], ouv[keep], used
    _check_views(n, ov, op, "tracks")
    rays = observation_rays(R, Kf, ov, ouv)
    P = len(track_ids)
    if config.init == "lud":
        C0, X0 = lud_positions(rays, ov, op, n, P, config.init_iterations)
        centroid = C0.mean(axis=0)
        radius = np.sqrt(np.mean(np.sum((C0 - centroid) ** 2, axis=1)))
        C0, X0 = (C0 - centroid) / radius, (X0 - centroid) / radius
    elif config.init == "random":
        rng = np.random.default_rng(config.seed)
        C0, X0 = rng.uniform(-1.0, 1.0, (n, 3)), rng.uniform(-1.0, 1.0, (P, 3))
    else:
        raise InputError(f"unknown start {config.init!r}", fix="use 'lud' or 'random'")
    w0 = X0[op] - C0[ov]
    d0 = np.maximum(np.sum(rays * w0, axis=1) / np.maximum(np.sum(w0 * w0, axis=1), 1e-300), _MIN_SCALE)
    z = np.r_[C0.ravel(), X0.ravel(), d0]
    problem = _Problem(rays, ov, op, n, P)
    z, it1, conv1 = _lm(problem, z, config)
    # Second round without the observations behind their camera or far off their ray.
    C, X, d = problem.split(z)
    w = X[op] - C[ov]
    cos = np.sum(rays * w, axis=1) / np.maximum(np.linalg.norm(w, axis=1), 1e-300)
    keep, remap, used = _keep_tracks(ov, op, cos > np.cos(np.radians(config.max_residual_deg)),
                                     max(2, config.min_track_length))
    _check_views(n, ov[keep], remap[op[keep]], "after dropping observations off their rays")
    ov, op, ouv, rays, track_ids = ov[keep], remap[op[keep]], ouv[keep], rays[keep], track_ids[used]
    z = np.r_[C.ravel(), X[used].ravel(), d[keep]]
    problem = _Problem(rays, ov, op, n, len(track_ids))
    z, it2, conv2 = _lm(problem, z, config)
    C, X, _ = problem.split(z)
    _check_collapse(rays, C, X, ov, op, config)
    t = -np.einsum("nij,nj->ni", R, C)
    return GlobalPositioningResult(
        cam_from_world=np.concatenate([R, t[:, :, None]], axis=2), points_xyz=X.copy(), track_ids=track_ids,
        obs_view=ov, obs_point=op, obs_uv=ouv, n_obs_per_view=np.bincount(ov, minlength=n),
        final_cost=problem.cost(z, config)[0], iterations=it1 + it2, converged=conv1 and conv2)


def _check_collapse(rays, C, X, ov, op, config: GlobalPositioningConfig) -> None:
    """Refuse a solution whose rays the rotations alone explain about as well (all centres effectively one)."""
    w = X[op] - C[ov]
    sin_solved = np.linalg.norm(np.cross(rays, w), axis=1) / np.maximum(np.linalg.norm(w, axis=1), 1e-300)
    mean_ray = np.zeros((int(op.max()) + 1, 3))
    np.add.at(mean_ray, op, rays)
    mean_ray /= np.maximum(np.linalg.norm(mean_ray, axis=1, keepdims=True), 1e-300)
    sin_rotation_only = np.linalg.norm(np.cross(rays, mean_ray[op]), axis=1)
    explained, solved = float(np.median(sin_rotation_only)), float(np.median(sin_solved))
    if explained <= config.min_parallax_ratio * solved + 1e-12:
        raise DegenerateGeometryError(
            f"global positioning: the solution collapses (pure rotation): the rotations alone leave a median "
            f"ray angle of {np.degrees(np.arcsin(min(explained, 1.0))):.3g} deg, the solved centres "
            f"{np.degrees(np.arcsin(min(solved, 1.0))):.3g} deg; no baseline between views {sorted(set(ov.tolist()))}")
