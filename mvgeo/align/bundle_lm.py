"""Levenberg-Marquardt bundle adjustment with the Schur complement (numpy, float64).

Unknowns: per view a pose ``cam_from_world`` (left-multiplicative rotation
update ``R <- exp([d]x) R``, translation), a log-focal shared by all views or
one per view, optionally one principal point shared by all views
(`LMProblem.optimize_principal`; else fixed), and per track a world point. View 0's
pose is fixed; the remaining scale freedom is held by the LM damping (the
metrics align by Sim(3) anyway). Residuals are reprojection errors in pixels
with a Huber loss, minimised by iteratively reweighted least squares: each
iteration solves the weighted normal equations with the point blocks (3x3)
eliminated, so the dense system has only ``6 (N - 1) + n_focal`` unknowns.

Analytic Jacobian of the projection ``p = f (x / z, y / z) + c`` of
``x_c = R X + t``:

    dp/dx_c = f / z [[1, 0, -x/z], [0, 1, -y/z]]
    dx_c/d(rot) = -[R X]x,  dx_c/dt = I,  dx_c/dX = R,  dp/dlog f = p - c,  dp/dc = I.

`mvgeo.align.bundle` keeps the scipy `least_squares` solver as the slow,
obvious reference (tests compare the two).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mvgeo.transforms import so3_exp


@dataclass
class LMProblem:
    """A bundle-adjustment problem (observations sorted arbitrarily).

    Attributes:
        ov: (K,) view of each observation.
        op: (K,) point of each observation.
        uv: (K, 2) observed pixels.
        f_index: (N,) focal unknown of each view (all 0 for a shared focal).
        c: (2,) principal point (the start, when `optimize_principal`).
        optimize_focal: False keeps the focals fixed.
        optimize_principal: the principal point, shared by all views, is an unknown (its two columns follow
            the focals' in the reduced camera system).
    """

    ov: np.ndarray
    op: np.ndarray
    uv: np.ndarray
    f_index: np.ndarray
    c: np.ndarray
    optimize_focal: bool = True
    optimize_principal: bool = False

    @property
    def n_principal(self) -> int:
        """Unknowns of the principal point (2 or 0)."""
        return 2 if self.optimize_principal else 0

    def with_principal(self, c: np.ndarray) -> LMProblem:
        """The same problem with principal point `c`."""
        return replace(self, c=np.asarray(c, np.float64))


def project(R: np.ndarray, t: np.ndarray, logf: np.ndarray, X: np.ndarray, pb: LMProblem):
    """(K, 2) residuals proj - uv and the camera-frame points (K, 3), rotated points (K, 3)."""
    RX = np.einsum("kij,kj->ki", R[pb.ov], X[pb.op])
    xc = RX + t[pb.ov]
    z = np.where(np.abs(xc[:, 2]) < 1e-12, 1e-12, xc[:, 2])
    f = np.exp(logf)[pb.f_index[pb.ov]]
    proj = f[:, None] * xc[:, :2] / z[:, None] + pb.c
    return proj - pb.uv, xc, RX, z, f


def _huber_weights(r: np.ndarray, k: float) -> np.ndarray:
    n = np.linalg.norm(r, axis=1)
    return np.where(n <= k, 1.0, k / np.maximum(n, 1e-300))


def _robust_cost(r: np.ndarray, k: float) -> float:
    n = np.linalg.norm(r, axis=1)
    return float(np.sum(np.where(n <= k, 0.5 * n * n, k * (n - 0.5 * k))))


def _columns(pb: LMProblem, n: int, nf: int) -> tuple[np.ndarray, int]:
    """(K, 7 + n_principal) global camera column of each observation's local unknowns (pose, focal, principal
    point; nc = dummy for fixed ones), nc."""
    npp = pb.n_principal
    nc = 6 * (n - 1) + nf + npp
    cols = np.full((len(pb.ov), 7 + npp), nc, np.int64)
    free = pb.ov > 0
    cols[free, :6] = (6 * (pb.ov[free] - 1))[:, None] + np.arange(6)
    if nf:
        cols[:, 6] = 6 * (n - 1) + pb.f_index[pb.ov]
    if npp:
        cols[:, 7:] = 6 * (n - 1) + nf + np.arange(npp)
    return cols, nc


@dataclass(frozen=True)
class Couplings:
    """The camera-point blocks ``W = J_c^T w J_p`` of the normal equations, one per observation.

    A point is seen by a few of the views, so W, as a dense (P, nc, 3) matrix, is mostly zeros; each
    observation k contributes the (m, 3) block `blocks[k]` at camera columns `cols[k]` and point `point[k]`
    (column `nc` is the dummy of fixed unknowns, dropped). The Schur complement and the back substitution
    work from these blocks (`reduced_camera_system`, `times_points`, `t_times_cameras`).

    Attributes:
        blocks: (K, m, 3), m = 7 (pose, focal) or 9 (and the principal point).
        cols: (K, m) camera column of each row of the block.
        point: (K,) point of each observation.
        n_cameras: nc, the camera unknowns.
        n_points: P.
    """

    blocks: np.ndarray
    cols: np.ndarray
    point: np.ndarray
    n_cameras: int
    n_points: int

    def dense(self) -> np.ndarray:
        """(P, nc, 3) W as a dense matrix (the tests' reference)."""
        return self.scatter(self.blocks).reshape(self.n_cameras, self.n_points, 3).transpose(1, 0, 2)

    def scatter(self, blocks: np.ndarray) -> np.ndarray:
        """(nc, 3 P) matrix of per-observation blocks (K, m, 3) laid out like W: row c, columns 3 p .. 3 p + 2
        hold the sum of the block rows at camera column c of point p's observations."""
        nc, P = self.n_cameras, self.n_points
        flat = ((self.cols * P + self.point[:, None])[:, :, None] * 3 + np.arange(3)).ravel()
        return np.bincount(flat, blocks.ravel(), minlength=(nc + 1) * P * 3)[:nc * P * 3].reshape(nc, P * 3)

    def times_points(self, v: np.ndarray) -> np.ndarray:
        """(nc,) sum over the points of W_p v_p, for v (P, 3)."""
        per_obs = np.einsum("kmj,kj->km", self.blocks, v[self.point])
        return np.bincount(self.cols.ravel(), per_obs.ravel(), minlength=self.n_cameras + 1)[:self.n_cameras]

    def t_times_cameras(self, dc: np.ndarray) -> np.ndarray:
        """(P, 3) W_p^T dc for every point, for dc (nc,)."""
        d = np.append(dc, 0.0)[self.cols]  # the dummy column reads 0
        per_obs = np.einsum("kmj,km->kj", self.blocks, d)
        return np.stack([np.bincount(self.point, per_obs[:, j], minlength=self.n_points) for j in range(3)],
                        axis=1)


def normal_equations(R, t, logf, X, pb: LMProblem, huber_px: float):
    """Blocks of the IRLS-weighted normal equations at the current state.

    Returns:
        U (nc, nc), gc (nc,), V (P, 3, 3), gp (P, 3), W (`Couplings`, per observation), residuals (K, 2).
    """
    n, P, K = len(R), len(X), len(pb.ov)
    nf = len(logf) if pb.optimize_focal else 0
    cols, nc = _columns(pb, n, nf)
    m = cols.shape[1]
    r, xc, RX, z, f = project(R, t, logf, X, pb)
    w = _huber_weights(r, huber_px)
    # d p / d x_c = [[a, 0, bx], [0, a, by]], written out per entry (batched 2x3 products are slower).
    iz = 1.0 / z
    a = f * iz
    bx = -a * xc[:, 0] * iz
    by = -a * xc[:, 1] * iz
    v0, v1, v2 = RX[:, 0], RX[:, 1], RX[:, 2]
    Jc = np.zeros((K, 2, m))
    # Rotation columns: -(d p / d x_c) [R X]x.
    Jc[:, 0, 0], Jc[:, 0, 1], Jc[:, 0, 2] = bx * v1, a * v2 - bx * v0, -a * v1
    Jc[:, 1, 0], Jc[:, 1, 1], Jc[:, 1, 2] = by * v1 - a * v2, -by * v0, a * v0
    Jc[:, 0, 3], Jc[:, 0, 5] = a, bx
    Jc[:, 1, 4], Jc[:, 1, 5] = a, by
    if nf:
        Jc[:, :, 6] = r + pb.uv - pb.c  # p - c
    if pb.optimize_principal:
        Jc[:, 0, 7] = Jc[:, 1, 8] = 1.0
    Jc[pb.ov == 0, :, :6] = 0.0
    Ro = R[pb.ov]
    Jp = np.stack([a[:, None] * Ro[:, 0] + bx[:, None] * Ro[:, 2],
                   a[:, None] * Ro[:, 1] + by[:, None] * Ro[:, 2]], axis=1)  # (K, 2, 3) = (d p / d x_c) R
    Jc_w = Jc * w[:, None, None]
    JcT_w = np.transpose(Jc_w, (0, 2, 1))
    # U: the observations of one view share their camera columns, so each view's block is one product.
    U = np.zeros((nc + 1, nc + 1))
    for v in range(n):
        k = np.flatnonzero(pb.ov == v)
        if len(k):
            cv = cols[k[0]]
            U[np.ix_(cv, cv)] += Jc_w[k].reshape(-1, m).T @ Jc[k].reshape(-1, m)
    U = U[:nc, :nc]
    gc = np.bincount(cols.ravel(), (JcT_w @ r[:, :, None]).ravel(), minlength=nc + 1)[:nc]
    Jp_w = Jp * w[:, None, None]
    Vk = Jp_w[:, 0, :, None] * Jp[:, 0, None, :] + Jp_w[:, 1, :, None] * Jp[:, 1, None, :]  # (K, 3, 3)
    V = np.stack([np.bincount(pb.op, Vk[:, i, j], minlength=P) for i in range(3) for j in range(3)],
                 axis=1).reshape(P, 3, 3)
    gk = Jp_w[:, 0] * r[:, 0, None] + Jp_w[:, 1] * r[:, 1, None]
    gp = np.stack([np.bincount(pb.op, gk[:, j], minlength=P) for j in range(3)], axis=1)
    W = Couplings(JcT_w @ Jp, cols, pb.op, nc, P)  # (K, 7 or 9, 3) blocks
    return U, gc, V, gp, W, r


def reduced_camera_system(U: np.ndarray, V: np.ndarray, W: Couplings, lam: float = 0.0
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Schur complement ``S = U - sum_p W_p V_p^-1 W_p^T`` (Marquardt damping lam on both diagonals) and the
    damped V^-1 (P, 3, 3).

    With ``V_p^-1 = L_p L_p^T`` (Cholesky) the sum is ``G G^T``, G (nc, 3 P) holding each observation's block
    times its point's L: one symmetric BLAS product over the (point, axis) index. The point blocks are
    positive definite (the ridge below); where a Cholesky factor still fails numerically, the sum is formed
    as ``W V^-1 W^T`` from two scatters instead.
    """
    Ud = U + lam * np.diag(np.diag(U) + 1e-12)
    # A tiny relative ridge keeps points seen along one ray (rank-2 V) invertible.
    tr = np.trace(V, axis1=1, axis2=2)[:, None, None]
    Vd = V + lam * (V * np.eye(3)) + (1e-10 * tr + 1e-12) * np.eye(3)
    Vinv = np.linalg.inv(Vd)
    try:
        G = W.scatter(W.blocks @ np.linalg.cholesky(Vinv)[W.point])
        S = Ud - G @ G.T
    except np.linalg.LinAlgError:
        S = Ud - W.scatter(W.blocks @ Vinv[W.point]) @ W.scatter(W.blocks).T
    return S, Vinv


def schur_step(U: np.ndarray, gc: np.ndarray, V: np.ndarray, gp: np.ndarray, W: Couplings, lam: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """The damped Gauss-Newton step (camera unknowns (nc,), points (P, 3)) of the normal equations
    ``[[U, W^T], [W, V]] [dc; dX] = -[gc; gp]`` (Marquardt damping `lam`): the reduced camera system solved
    for dc, then each point's dX by back substitution.

    Raises:
        numpy.linalg.LinAlgError: the reduced system is singular.
    """
    S, Vinv = reduced_camera_system(U, V, W, lam)
    rhs = -gc + W.times_points(np.einsum("pij,pj->pi", Vinv, gp))
    dc = np.linalg.solve(S, rhs) if len(rhs) else np.zeros(0)
    return dc, -np.einsum("pij,pj->pi", Vinv, gp + W.t_times_cameras(dc))


def solve_lm(R: np.ndarray, t: np.ndarray, logf: np.ndarray, X: np.ndarray, pb: LMProblem, *,
             huber_px: float, max_iters: int = 50, tol: float = 1e-10
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Minimise the Huber reprojection cost; returns refined (R, t, logf, X, iterations). With
    `pb.optimize_principal` the refined principal point is `solve_lm_principal`'s; this function is that
    one without it."""
    R, t, logf, X, _, it = solve_lm_principal(R, t, logf, X, pb, huber_px=huber_px, max_iters=max_iters, tol=tol)
    return R, t, logf, X, it


def solve_lm_principal(R: np.ndarray, t: np.ndarray, logf: np.ndarray, X: np.ndarray, pb: LMProblem, *,
                       huber_px: float, max_iters: int = 50, tol: float = 1e-10
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Minimise the Huber reprojection cost; returns refined (R, t, logf, X, principal point (2,), iterations)
    (the principal point is `pb.c` unless `pb.optimize_principal`)."""
    n = len(R)
    nf = len(logf) if pb.optimize_focal else 0
    lam = 1e-3
    cost = _robust_cost(project(R, t, logf, X, pb)[0], huber_px)
    it = 0
    for it in range(1, max_iters + 1):  # noqa: B007
        U, gc, V, gp, W, _ = normal_equations(R, t, logf, X, pb, huber_px)
        improved, rel = False, 0.0
        for _ in range(10):
            try:
                dc, dX = schur_step(U, gc, V, gp, W, lam)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            R1, t1, lf1, pb1 = R.copy(), t.copy(), logf.copy(), pb
            if n > 1:
                d = dc[:6 * (n - 1)].reshape(n - 1, 6)
                R1[1:] = np.stack([so3_exp(v) for v in d[:, :3]]) @ R[1:]
                t1[1:] = t[1:] + d[:, 3:]
            if nf:
                lf1 = logf + dc[6 * (n - 1):6 * (n - 1) + nf]
            if pb.optimize_principal:
                pb1 = pb.with_principal(pb.c + dc[6 * (n - 1) + nf:])
            X1 = X + dX
            r1 = project(R1, t1, lf1, X1, pb1)[0]
            cost1 = _robust_cost(r1, huber_px) if np.all(np.isfinite(r1)) else np.inf
            if cost1 < cost:
                rel = (cost - cost1) / max(cost, 1e-300)
                R, t, logf, X, pb, cost = R1, t1, lf1, X1, pb1, cost1
                lam = max(lam / 3.0, 1e-9)
                improved = True
                break
            lam *= 4.0
        if not improved or rel < tol:
            break
    return R, t, logf, X, np.asarray(pb.c, np.float64), it


def principal_step(R, t, logf, X, pb: LMProblem, huber_px: float) -> tuple[np.ndarray, np.ndarray]:
    """((2,) principal point, (2,) its standard deviation) one Gauss-Newton step from the given state with the
    principal point free (`pb.optimize_principal`), points marginalised, and its standard deviation at the
    given state (Laplace approximation, residual variance from the residuals, as `log_focal_std`).

    From a solution converged with the principal point fixed, the step is the linearised joint optimum. On
    close views the cost is so flat along the principal point that LM with its damping creeps there (DTU
    scan24: 50 iterations, 0.7 s, where this takes one solve). The scale gauge is a null direction of the
    reduced system that does not move the principal point: a pseudo-inverse gives its component.
    """
    if not pb.optimize_principal:
        raise ValueError("principal_step needs LMProblem.optimize_principal")
    n = len(R)
    nf = len(logf) if pb.optimize_focal else 0
    U, gc, V, gp, W, r = normal_equations(R, t, logf, X, pb, huber_px)
    S, Vinv = reduced_camera_system(U, V, W)
    rhs = -gc + W.times_points(np.einsum("pij,pj->pi", Vinv, gp))
    Sinv = np.linalg.pinv(S, rcond=1e-12, hermitian=True)
    k = 6 * (n - 1) + nf
    dof = max(r.size - len(S) - 3 * len(X), 1)
    sigma2 = float(np.sum(r * r)) / dof
    return pb.c + (Sinv @ rhs)[k:k + 2], np.sqrt(np.maximum(np.diag(Sinv)[k:k + 2] * sigma2, 0.0))


def principal_std(R, t, logf, X, pb: LMProblem, huber_px: float) -> np.ndarray:
    """(2,) standard deviation (pixels) of the shared principal point, as `log_focal_std` (Laplace
    approximation, points marginalised, residual variance from the residuals; `principal_step`'s); zeros
    unless `pb.optimize_principal`."""
    if not pb.optimize_principal:
        return np.zeros(2)
    return principal_step(R, t, logf, X, pb, huber_px)[1]


def log_focal_std(R, t, logf, X, pb: LMProblem, huber_px: float) -> np.ndarray:
    """(n_focal,) standard deviation of each log-focal (Laplace approximation, points marginalised).

    The residual variance is estimated from the residuals; the scale gauge is a
    null direction of the reduced system that leaves the focals unchanged, so a
    pseudo-inverse gives their marginal variance.
    """
    n = len(R)
    nf = len(logf)
    if not pb.optimize_focal or nf == 0:
        return np.zeros(nf)
    U, _, V, _, W, r = normal_equations(R, t, logf, X, pb, huber_px)
    S = reduced_camera_system(U, V, W)[0]
    dof = max(r.size - len(S) - 3 * len(X), 1)
    sigma2 = float(np.sum(r * r)) / dof
    cov = np.linalg.pinv(S, rcond=1e-12, hermitian=True) * sigma2
    k = 6 * (n - 1)
    return np.sqrt(np.maximum(np.diag(cov)[k:k + nf], 0.0))



def _view_blocks(R, t, logf, X, pb: LMProblem, huber_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, 6, 6) reduced-system block of every view's pose (points marginalised, the other views and the
    focals held), and the residuals. View 0 is fixed in `normal_equations`: its block comes from a second
    call with views 0 and 1 swapped."""
    n = len(R)
    blocks = np.zeros((n, 6, 6))
    U, _, V, _, W, r = normal_equations(R, t, logf, X, pb, huber_px)
    S = reduced_camera_system(U, V, W)[0]
    for v in range(1, n):
        blocks[v] = S[6 * (v - 1):6 * v, 6 * (v - 1):6 * v]
    swap = np.arange(n)
    swap[[0, 1]] = [1, 0]
    pb1 = LMProblem(swap[pb.ov], pb.op, pb.uv, pb.f_index[swap], pb.c, pb.optimize_focal, pb.optimize_principal)
    U1, _, V1, _, W1, _ = normal_equations(R[swap], t[swap], logf, X, pb1, huber_px)
    blocks[0] = reduced_camera_system(U1, V1, W1)[0][:6, :6]  # old view 0 is now view 1
    return blocks, r


#: `camera_centre_std`: a view's 6x6 block whose smallest eigenvalue is at most this times its largest is
#: singular (rounding in the Schur complement leaves ~1e-16 relative; a determined view measured 3e-4).
_SINGULAR_BLOCK_RCOND = 1e-12


def camera_centre_std(R, t, logf, X, pb: LMProblem, huber_px: float) -> np.ndarray:
    """(N,) largest standard deviation of each camera centre (world units) when the other cameras are held.

    How well the tracks pin each camera: the Laplace approximation of its pose
    given every other pose and the focals, with the points marginalised (the
    view's 6x6 block of the reduced camera system), the residual variance
    estimated from the residuals. Holding the others removes the gauge (the
    similarity of the whole scene) without choosing one, and charges a loose
    camera to itself: a view tied to the rest by two-view tracks only gets a
    direction from each pair but no distance, so its block is (near) singular
    along that direction. A centre c = -R^T t moves by ``-R^T dt - R^T [t]x d``
    under the update (d, dt) of its rotation and translation. A block that is
    singular to rounding (a view with too few observations to fix its six pose
    parameters, e.g. two points) gives inf: its inverse is rounding noise of
    either sign, and its largest eigenvalue alone can look small.
    """
    n = len(R)
    if n < 2:
        return np.zeros(n)
    blocks, r = _view_blocks(R, t, logf, X, pb, huber_px)
    dof = max(r.size - 6 * (n - 1) - len(logf) - pb.n_principal - 3 * len(X), 1)
    sigma2 = float(np.sum(r * r)) / dof
    out = np.empty(n)
    for v in range(n):
        tx = np.array([[0.0, -t[v][2], t[v][1]], [t[v][2], 0.0, -t[v][0]], [-t[v][1], t[v][0], 0.0]])
        J = np.concatenate([-R[v].T @ tx, -R[v].T], axis=1)
        try:
            w, Q = np.linalg.eigh(0.5 * (blocks[v] + blocks[v].T))
        except np.linalg.LinAlgError:
            out[v] = np.inf
            continue
        if not (np.all(np.isfinite(w)) and w[0] > _SINGULAR_BLOCK_RCOND * w[-1]):
            out[v] = np.inf
            continue
        JQ = J @ Q
        cc = (JQ / w) @ JQ.T * sigma2
        out[v] = float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (cc + cc.T))[-1], 0.0)))
    return out
