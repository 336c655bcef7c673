"""Global positioning against the true centres, finite differences and a slow scipy minimiser of the same cost."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, diags
from scipy.spatial.transform import Rotation

from mvgeo.align.lud import lud_positions
from mvgeo.align.translation_averaging import (
    _MIN_SCALE,
    GlobalPositioningConfig,
    _damped_step,
    _damped_step_sparse,
    _loss,
    _Normal,
    _Problem,
    global_positions,
    observation_rays,
)
from mvgeo.common.errors import DegenerateGeometryError, InputError
from mvgeo.transforms import umeyama

W_PX, H_PX, F_PX = 640, 480, 500.0


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(3, 3) R of cam_from_world for a camera at `centre` looking at `target`, image y pointing down (world -y)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _scene(kind: str, *, n_views: int = 8, n_points: int = 300, seed: int = 0, px_noise: float = 0.0,
           rot_noise_deg: float = 0.0, outlier_frac: float = 0.0, baseline: float = 1.0):
    """Cameras, points and all-pairs matches, projected with plain numpy.

    "ring": 8 cameras on a radius-4 circle looking at points in a 3 m cube at the centre; "row": a
    forward-facing row 2 m wide (times `baseline`) of cameras looking at points 4-10 m ahead. Pixel noise
    is drawn once per (view, point), so the matches of one keypoint agree and form tracks; a fraction
    `outlier_frac` of the keypoints is replaced by a uniform random pixel (a wrong observation in every
    match it takes part in). The returned rotations carry `rot_noise_deg` RMS rotation noise.

    Returns:
        R_noisy (N, 3, 3), K (N, 3, 3), true centres (N, 3), true points (P, 3), matches.
    """
    rng = np.random.default_rng(seed)
    if kind == "ring":
        a = 2 * np.pi * np.arange(n_views) / n_views
        C = np.stack([4 * np.cos(a), 0.3 * np.sin(3 * a), 4 * np.sin(a)], 1)
        R = np.stack([_look_at(c, np.zeros(3)) for c in C])
        X = rng.uniform(-1.5, 1.5, (n_points, 3))
    else:
        C = baseline * np.stack([np.linspace(-1, 1, n_views), 0.1 * rng.normal(size=n_views),
                                 0.1 * rng.normal(size=n_views)], 1)
        R = Rotation.from_rotvec(np.radians(3.0) * rng.normal(size=(n_views, 3))).as_matrix()
        depth = rng.uniform(4, 10, n_points)
        X = np.stack([rng.uniform(-0.5, 0.5, n_points) * depth, rng.uniform(-0.35, 0.35, n_points) * depth, depth], 1)
    K = np.tile(np.array([[F_PX, 0, W_PX / 2], [0, F_PX, H_PX / 2], [0, 0, 1.0]]), (n_views, 1, 1))
    uv = np.zeros((n_views, n_points, 2))
    seen = np.zeros((n_views, n_points), bool)
    for n in range(n_views):
        x_cam = (X - C[n]) @ R[n].T
        p = x_cam[:, :2] / x_cam[:, 2:] * F_PX + [W_PX / 2, H_PX / 2]
        uv[n] = p + px_noise * rng.normal(size=p.shape)
        seen[n] = (x_cam[:, 2] > 0.1) & np.all((p > 0) & (p < [W_PX, H_PX]), 1)
    bad = rng.random((n_views, n_points)) < outlier_frac
    uv[bad] = rng.uniform([0, 0], [W_PX, H_PX], (int(bad.sum()), 2))
    matches = []
    for i in range(n_views):
        for j in range(i + 1, n_views):
            m = seen[i] & seen[j]
            matches.append((i, j, np.concatenate([uv[i, m], uv[j, m]], 1)))
    noise = Rotation.from_rotvec(np.radians(rot_noise_deg) * rng.normal(size=(n_views, 3)) / np.sqrt(3)).as_matrix()
    return noise @ R, K, C, X, matches


def _centres(cam_from_world: np.ndarray) -> np.ndarray:
    return -np.einsum("nji,nj->ni", cam_from_world[:, :, :3], cam_from_world[:, :, 3])


def _relative_error(C_est: np.ndarray, C_true: np.ndarray) -> float:
    """RMS centre error after the best Sim(3), over the RMS radius of the true centres."""
    sim = umeyama(C_est, C_true)
    rms = np.sqrt(np.mean(np.sum((sim.apply(C_est) - C_true) ** 2, axis=1)))
    return float(rms / np.sqrt(np.mean(np.sum((C_true - C_true.mean(0)) ** 2, axis=1))))


def _first_order_bound(C, X, matches, rot_noise_deg, px_noise) -> float:
    """Twice the first-order relative centre error of rotation and pixel noise (see the test using it).

    A view rotated by delta moves all its rays by delta; with a field of view well under 90 deg this is
    matched best by moving the centre sideways by about D * delta (D: the distance to the points), so a
    centre error of D * sigma_R follows, relative: D / rho * sigma_R (rho: RMS radius of the centres).
    Pixel noise sigma_px / f per ray averages over the M >= M_min rays of a view: D / rho * sigma_px /
    (f sqrt(M_min)). The factor 2 covers the first-order approximation; it is not fitted to the results.
    """
    rho = np.sqrt(np.mean(np.sum((C - C.mean(0)) ** 2, axis=1)))
    dist = np.linalg.norm(X[None] - C[:, None], axis=2)
    m_min = min(len(np.unique(np.concatenate([uv[:, :2] for i, _, uv in matches if i == n]
                                             + [uv[:, 2:] for _, j, uv in matches if j == n]), axis=0))
                for n in range(len(C)))
    return 2.0 * float(np.median(dist)) / rho * (np.radians(rot_noise_deg) + px_noise / (F_PX * np.sqrt(m_min)))


@pytest.mark.parametrize("kind", ["ring", "row"])
def test_noiseless_recovers_centres_up_to_similarity(kind):
    R, K, C, X, matches = _scene(kind)
    res = global_positions(R, K, matches)
    C_est = _centres(res.cam_from_world)
    assert _relative_error(C_est, C) < 1e-6
    # The gauge: centroid 0, RMS radius 1; rotations are the inputs.
    np.testing.assert_allclose(C_est.mean(0), 0.0, atol=1e-9)
    assert np.sqrt(np.mean(np.sum(C_est**2, axis=1))) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_array_equal(res.cam_from_world[:, :, :3], R)
    # Points on their rays, per-view counts consistent with the observations returned.
    rays = observation_rays(R, K, res.obs_view, res.obs_uv)
    w = res.points_xyz[res.obs_point] - C_est[res.obs_view]
    assert np.max(np.linalg.norm(np.cross(rays, w / np.linalg.norm(w, axis=1, keepdims=True)), axis=1)) < 1e-7
    np.testing.assert_array_equal(res.n_obs_per_view, np.bincount(res.obs_view, minlength=len(R)))
    assert len(res.track_ids) == len(res.points_xyz) and res.converged


@pytest.mark.parametrize("kind", ["ring", "row"])
def test_pixel_and_rotation_noise_within_first_order_bound(kind):
    R, K, C, X, matches = _scene(kind, seed=1, px_noise=0.5, rot_noise_deg=0.1)
    err = _relative_error(_centres(global_positions(R, K, matches).cam_from_world), C)
    assert err < _first_order_bound(C, X, matches, 0.1, 0.5)


def test_robust_loss_bounds_the_error_of_wrong_observations():
    R, K, C, X, matches = _scene("ring", seed=2, px_noise=0.5, rot_noise_deg=0.1, outlier_frac=0.1)
    bound = _first_order_bound(C, X, matches, 0.1, 0.5)
    # Without the second-round filter, so that only the loss stands between the wrong rays and the centres.
    no_filter = dict(max_residual_deg=180.0)
    robust = _relative_error(_centres(global_positions(R, K, matches, GlobalPositioningConfig(
        **no_filter)).cam_from_world), C)
    plain = _relative_error(_centres(global_positions(R, K, matches, GlobalPositioningConfig(
        loss="trivial", **no_filter)).cam_from_world), C)
    assert robust < bound
    assert plain > 3.0 * robust
    # The defaults (loss and filter) on the forward-facing row, the harder geometry.
    R, K, C, X, matches = _scene("row", seed=2, px_noise=0.5, rot_noise_deg=0.1, outlier_frac=0.1)
    assert _relative_error(_centres(global_positions(R, K, matches).cam_from_world), C) < _first_order_bound(
        C, X, matches, 0.1, 0.5)


def test_random_start_reaches_the_same_solution():
    R, K, C, X, matches = _scene("ring", n_views=4, n_points=30, seed=3)
    res = global_positions(R, K, matches, GlobalPositioningConfig(init="random", max_iters=400, seed=5))
    assert _relative_error(_centres(res.cam_from_world), C) < 1e-6


def test_disconnected_views_raise():
    R, K, C, X, matches = _scene("row")
    split = [(i, j, uv) for i, j, uv in matches if (i < 4) == (j < 4)]
    with pytest.raises(DegenerateGeometryError, match=r"not connected.*\[0, 1, 2, 3\]"):
        global_positions(R, K, split)


def test_view_without_observations_raises():
    R, K, C, X, matches = _scene("row")
    with pytest.raises(DegenerateGeometryError, match=r"views \[7\] have no usable observations"):
        global_positions(R, K, [(i, j, uv) for i, j, uv in matches if 7 not in (i, j)])


@pytest.mark.parametrize("px_noise", [0.0, 0.5])
def test_all_cameras_at_one_centre_raise(px_noise):
    R, K, C, X, matches = _scene("row", n_views=5, n_points=60, baseline=0.0, px_noise=px_noise)
    assert np.all(C == 0.0)
    with pytest.raises(DegenerateGeometryError, match="collapses"):
        global_positions(R, K, matches)


def test_bad_input_raises():
    R, K, C, X, matches = _scene("row", n_views=3, n_points=20)
    with pytest.raises(InputError, match="unknown loss"):
        global_positions(R, K, matches, GlobalPositioningConfig(loss="l1"))
    with pytest.raises(InputError, match="not two distinct views"):
        global_positions(R, K, matches + [(0, 3, matches[0][2])])


def _small_problem(seed: int):
    R, K, C, X, matches = _scene("ring", n_views=4, n_points=30, seed=seed, px_noise=0.5)
    res = global_positions(R, K, matches)
    rays = observation_rays(R, K, res.obs_view, res.obs_uv)
    return res, _Problem(rays, res.obs_view, res.obs_point, len(R), len(res.points_xyz)), C


def test_jacobian_matches_finite_differences():
    _, problem, _ = _small_problem(4)
    rng = np.random.default_rng(0)
    z = np.r_[rng.normal(size=3 * problem.n + 3 * problem.p), rng.uniform(0.5, 2.0, problem.k)]
    J = problem.jacobian(z).toarray()
    h = 1e-6
    J_fd = np.empty_like(J)
    for c in range(len(z)):
        dz = np.zeros_like(z)
        dz[c] = h
        plus, minus = problem.residuals(z + dz), problem.residuals(z - dz)
        J_fd[:, c] = (np.r_[plus[0].ravel(), plus[1]] - np.r_[minus[0].ravel(), minus[1]]) / (2 * h)
    # Central differences of (at most quadratic) residuals: error ~ h^2 * third derivative = 0, plus rounding.
    np.testing.assert_allclose(J, J_fd, atol=1e-7)


def test_matches_scipy_least_squares_on_the_same_cost():
    """The IRLS-LM with the Schur step against MINPACK's LM (scipy, dense finite-difference Jacobian).

    Scipy's robust losses act on each scalar residual, ours on the norm of each 3-vector, so the reference
    minimises the same cost written with plain least squares: each 3-vector scaled to squared norm rho(|r|^2),
    ``r * sqrt(rho(|r|^2) / |r|^2)``, plus the 4 gauge residuals. MINPACK takes no bounds; the scales' bound
    is inactive at this optimum (asserted). It starts from the LUD start, not from our answer.
    """
    res, problem, _ = _small_problem(5)
    config = GlobalPositioningConfig()
    C0, X0 = lud_positions(problem.v, problem.ov, problem.op, problem.n, problem.p, 50)
    w0 = X0[problem.op] - C0[problem.ov]
    z0 = np.r_[C0.ravel(), X0.ravel(), np.maximum(np.sum(problem.v * w0, 1) / np.sum(w0 * w0, 1), _MIN_SCALE)]

    def fun(z):
        r, g = problem.residuals(z)
        s2 = np.sum(r * r, axis=1)
        return np.r_[(r * np.sqrt(_loss(s2, config.loss, config.loss_scale)[0] / s2)[:, None]).ravel(), g]

    ref = least_squares(fun, z0, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    d_ref = ref.x[3 * (problem.n + problem.p):]
    assert ref.success and d_ref.min() > 100 * _MIN_SCALE
    k3 = 3 * problem.k
    assert 0.5 * float(ref.fun[:k3] @ ref.fun[:k3]) == pytest.approx(res.final_cost, rel=1e-6)
    # Centres have RMS radius 1; both solvers stop at ~1e-12 steps.
    np.testing.assert_allclose(_centres(res.cam_from_world), ref.x[:3 * problem.n].reshape(-1, 3), atol=1e-8)


@pytest.mark.parametrize("duplicate", [False, True])
@pytest.mark.parametrize("lam", [0.0, 1e-4, 10.0])
def test_block_step_equals_the_sparse_reference(lam, duplicate):
    """`_damped_step` (blocks; the points' Schur term as one product of sparse block matrices) against
    `_damped_step_sparse` (scipy.sparse products of the Jacobian), at a state off the optimum with IRLS
    weights and some scales held; also with observations repeated (a track seeing one view twice)."""
    _, problem, _ = _small_problem(5)
    if duplicate:
        rep = np.arange(0, problem.k, 7)
        problem = _Problem(np.r_[problem.v, problem.v[rep]], np.r_[problem.ov, problem.ov[rep]],
                           np.r_[problem.op, problem.op[rep]], problem.n, problem.p)
    rng = np.random.default_rng(1)
    z = np.r_[rng.normal(size=3 * problem.n + 3 * problem.p), rng.uniform(0.5, 2.0, problem.k)]
    r, _ = problem.residuals(z)
    wt = rng.uniform(0.2, 1.0, problem.k)
    free = rng.uniform(size=problem.k) > 0.1
    nq = _Normal(problem, z, wt)
    D = np.clip(nq.diagonal(), 1e-12, 1e32)
    ref = _damped_step_sparse(problem, z, wt, lam, free)
    fast = _damped_step(nq, lam, D, free)
    assert np.all(ref[3 * problem.n + 3 * problem.p:][~free] == 0.0)
    # The same linear system solved in another order: agreement to rounding, relative to the step.
    np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    # The blocks' diagonal is the sparse H's (the damping uses it).
    sw = np.r_[np.repeat(np.sqrt(wt), 3), np.ones(4)]
    J = (diags(sw) @ problem.jacobian(z)).toarray()
    np.testing.assert_allclose(nq.diagonal(), np.sum(J * J, axis=0), rtol=1e-12, atol=1e-12)



def _lud_reference(rays: np.ndarray, obs_view: np.ndarray, obs_point: np.ndarray, n_views: int, n_points: int,
                        iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """`lud_positions` in its textbook form: the (C, X) normal equations from the sparse incidence matrices A (views)
    and B (points) of r = B X + A C - d v, X eliminated per track."""
    k = len(rays)
    A = coo_matrix((-np.ones(k), (np.arange(k), obs_view)), shape=(k, n_views)).tocsr()  # r = B X + A C - d v
    B = coo_matrix((np.ones(k), (np.arange(k), obs_point)), shape=(k, n_points)).tocsr()
    d, weight = np.ones(k), np.ones(k)
    for _ in range(iterations):
        b = d[:, None] * rays
        W = diags(weight)
        w_point = np.bincount(obs_point, weight, minlength=n_points)
        AWB = (A.T @ W @ B).tocsr()
        S = (A.T @ W @ A).toarray() - (AWB @ diags(1.0 / w_point) @ AWB.T).toarray()
        S += np.full((n_views, n_views), weight.sum() / (k * n_views))
        BWb = B.T @ (weight[:, None] * b)
        C = np.linalg.solve(S, A.T @ (weight[:, None] * b) - AWB @ (BWb / w_point[:, None]))
        X = (BWb - AWB.T @ C) / w_point[:, None]
        w = X[obs_point] - C[obs_view]
        d = np.maximum(1.0, np.sum(w * rays, axis=1))
        r = np.linalg.norm(w - d[:, None] * rays, axis=1)
        weight = 1.0 / np.maximum(r, 1e-6 * max(float(np.median(r)), 1e-300))
    return C, X


@pytest.mark.parametrize("duplicate", [False, True])
def test_lud_start_equals_the_sparse_reference(duplicate):
    """`lud_positions` (per-view and per-point sums, one sparse (view, point) matrix) against `_lud_reference`
    (the incidence products): the same alternations, so the same centres and points to rounding; also with
    observations repeated (a track seeing one view twice adds to one (view, point) cell)."""
    _, problem, _ = _small_problem(5)
    if duplicate:
        rep = np.arange(0, problem.k, 7)
        problem = _Problem(np.r_[problem.v, problem.v[rep]], np.r_[problem.ov, problem.ov[rep]],
                           np.r_[problem.op, problem.op[rep]], problem.n, problem.p)
    for iterations in (1, 20):
        C, X = lud_positions(problem.v, problem.ov, problem.op, problem.n, problem.p, iterations)
        C_ref, X_ref = _lud_reference(problem.v, problem.ov, problem.op, problem.n, problem.p, iterations)
        # Centres of RMS radius ~1; 20 IRLS reweightings amplify rounding by at most a few orders.
        np.testing.assert_allclose(C, C_ref, rtol=0, atol=1e-9)
        np.testing.assert_allclose(X, X_ref, rtol=0, atol=1e-9 * max(1.0, np.abs(X_ref).max()))
