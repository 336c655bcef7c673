"""OpenCV-family lens distortion on normalised image coordinates (numpy float64 kernels).

One parameterisation covers every supported model: the 8-vector
``dist = [k1, k2, p1, p2, k3, k4, k5, k6]`` (OpenCV's / COLMAP FULL_OPENCV's /
mrcal OPENCV8's order). SIMPLE_RADIAL is ``[k, 0, ...]``, OPENCV is
``[k1, k2, p1, p2, 0, 0, 0, 0]``, pinhole models are all zeros.

With ``r^2 = x^2 + y^2``, ``a = 1 + k1 r^2 + k2 r^4 + k3 r^6``,
``b = 1 + k4 r^2 + k5 r^4 + k6 r^6``::

    xd = x a/b + 2 p1 x y + p2 (r^2 + 2 x^2)
    yd = y a/b + p1 (r^2 + 2 y^2) + 2 p2 x y

Validity: the model is only a usable lens model where the radial map
``r -> r a(r)/b(r)`` is increasing and ``b > 0`` (beyond that radius,
projection folds back and distinct rays land on the same pixel). Points
outside that region are flagged invalid rather than projected silently. The
region is the disc up to the *first* radius where the map stops increasing
(or ``b`` reaches 0), not every radius where it happens to increase: with
``k1 < 0 < k2`` the map can rise again further out, and a ray there lands on
a pixel that a ray inside the disc also reaches.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ["DistortResult", "distort", "UndistortResult", "undistort"]


@dataclass(frozen=True)
class DistortResult:
    """Distorted normalised coordinates and derivatives.

    Attributes:
        xy_dist: (..., 2).
        d_xy: (..., 2, 2) Jacobian ``d xy_dist / d xy``.
        d_dist: (..., 2, 8) Jacobian w.r.t. ``[k1, k2, p1, p2, k3, k4, k5, k6]``.
        valid: (...) bool, inside the model's valid disc (module docstring): the radial map increases and
            ``b > 0`` from the centre out to the point.
    """

    xy_dist: np.ndarray
    d_xy: np.ndarray
    d_dist: np.ndarray
    valid: np.ndarray


def _first_positive_root(coeffs: np.ndarray) -> float:
    """Smallest ``s > 0`` where the polynomial (coefficients lowest order first) reaches 0, or inf.

    Real roots count; a complex pair close to the real axis counts where the polynomial is <= 0 at its real
    part (a dip below zero that rounding turned into a complex pair).
    """
    c = np.trim_zeros(np.asarray(coeffs, dtype=np.float64), "b")
    if c.size <= 1:
        return np.inf
    roots = np.roots(c[::-1])
    re = roots.real
    keep = (re > 0) & ((roots.imag == 0) | (np.polynomial.polynomial.polyval(re, c) <= 0))
    return float(re[keep].min()) if np.any(keep) else np.inf


@lru_cache(maxsize=64)
def _valid_radius2(dist: tuple[float, ...]) -> float:
    """Squared radius ``s = r^2`` of the model's valid disc for ``dist`` (8,): the first ``s > 0`` where
    ``d(r a/b)/dr`` or ``b`` reaches 0 (inf when neither does)."""
    k1, k2, _, _, k3, k4, k5, k6 = dist
    P = np.polynomial.polynomial
    a = np.array([1.0, k1, k2, k3])
    b = np.array([1.0, k4, k5, k6])
    # d(r a/b)/dr = N(s) / b^2 with N = a b + 2 s (a' b - a b'), ' = d/ds.
    n = P.polyadd(P.polymul(a, b), 2 * P.polymulx(P.polysub(P.polymul(P.polyder(a), b), P.polymul(a, P.polyder(b)))))
    return min(_first_positive_root(n), _first_positive_root(b))


def distort(xy, dist) -> DistortResult:
    """Apply the distortion to normalised coordinates.

    Args:
        xy: (..., 2) undistorted normalised coordinates ``(X/Z, Y/Z)``.
        dist: (8,) ``[k1, k2, p1, p2, k3, k4, k5, k6]``.

    Returns:
        `DistortResult` (float64).
    """
    xy = np.asarray(xy, dtype=np.float64)
    k1, k2, p1, p2, k3, k4, k5, k6 = np.asarray(dist, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    a = 1 + k1 * r2 + k2 * r4 + k3 * r6
    b = 1 + k4 * r2 + k5 * r4 + k6 * r6
    b_safe = np.where(b > 0, b, 1.0)
    rad = a / b_safe
    da = k1 + 2 * k2 * r2 + 3 * k3 * r4  # d a / d r^2
    db = k4 + 2 * k5 * r2 + 3 * k6 * r4
    drad = (da * b - a * db) / (b_safe * b_safe)  # d rad / d r^2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    d_xy = np.empty(xy.shape[:-1] + (2, 2))
    d_xy[..., 0, 0] = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    d_xy[..., 0, 1] = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    d_xy[..., 1, 0] = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    d_xy[..., 1, 1] = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    d_rad = np.stack([r2 / b_safe, r4 / b_safe, r6 / b_safe,
                      -rad * r2 / b_safe, -rad * r4 / b_safe, -rad * r6 / b_safe], axis=-1)  # k1 k2 k3 k4 k5 k6
    d_dist = np.zeros(xy.shape[:-1] + (2, 8))
    cols = [0, 1, 4, 5, 6, 7]
    d_dist[..., 0, cols] = x[..., None] * d_rad
    d_dist[..., 1, cols] = y[..., None] * d_rad
    d_dist[..., 0, 2] = 2 * x * y
    d_dist[..., 1, 2] = r2 + 2 * y * y
    d_dist[..., 0, 3] = r2 + 2 * x * x
    d_dist[..., 1, 3] = 2 * x * y
    # Monotonic radial map: d(r rad)/dr = rad + 2 r^2 drad > 0 here and at every smaller radius.
    s_max = _valid_radius2(tuple(float(v) for v in (k1, k2, p1, p2, k3, k4, k5, k6)))
    valid = (r2 < s_max) & (b > 0) & (rad + 2 * r2 * drad > 0) & np.isfinite(xd) & np.isfinite(yd)
    return DistortResult(xy_dist=np.stack([xd, yd], -1), d_xy=d_xy, d_dist=d_dist, valid=valid)


@dataclass(frozen=True)
class UndistortResult:
    """Undistorted normalised coordinates from Newton iterations.

    Attributes:
        xy: (..., 2) undistorted coordinates (finite everywhere; meaningless where not valid).
        converged: (...) bool, residual ``|distort(xy) - xy_dist| <= tol`` reached.
        valid: (...) bool, converged *and* inside the model's valid region.
        residual: (...) final residual in normalised units.
        iterations: number of iterations run (max over the batch).
    """

    xy: np.ndarray
    converged: np.ndarray
    valid: np.ndarray
    residual: np.ndarray
    iterations: int


def undistort(xy_dist, dist, *, tol: float = 1e-12, max_iterations: int = 50) -> UndistortResult:
    """Invert `distort` by damped Newton's method, per point, vectorised.

    Starts at ``xy_dist`` (exact for zero distortion). A Newton step that
    would leave the valid region or increase the residual is halved (up to
    10 times). Points whose Jacobian is singular or that fail to reach
    ``tol`` are reported not converged; their ``xy`` is the last finite
    iterate.

    Args:
        xy_dist: (..., 2) distorted normalised coordinates.
        dist: (8,) ``[k1, k2, p1, p2, k3, k4, k5, k6]``.
        tol: convergence threshold on the residual (normalised units; 1e-12
            is ~1e-9 px for a focal length of 1000 px).
        max_iterations: Newton iterations.

    Returns:
        `UndistortResult`.
    """
    target = np.asarray(xy_dist, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64)
    xy = np.where(np.isfinite(target), target, 0.0)
    if not np.any(dist):
        res = np.where(np.all(np.isfinite(target), axis=-1), 0.0, np.inf)
        ok = res == 0
        return UndistortResult(xy=xy, converged=ok, valid=ok, residual=res, iterations=0)
    cur = distort(xy, dist)
    err = cur.xy_dist - target
    res = np.linalg.norm(err, axis=-1)
    res = np.where(np.isfinite(res), res, np.inf)
    iterations = 0
    for _ in range(max_iterations):
        active = res > tol
        if not np.any(active):
            break
        iterations += 1
        J = cur.d_xy
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        det_safe = np.where(np.abs(det) > 1e-300, det, 1.0)
        step = np.stack([J[..., 1, 1] * err[..., 0] - J[..., 0, 1] * err[..., 1],
                         -J[..., 1, 0] * err[..., 0] + J[..., 0, 0] * err[..., 1]], -1) / det_safe[..., None]
        step = np.where((active & (np.abs(det) > 1e-300))[..., None], step, 0.0)
        alpha = np.ones(res.shape)
        for _ in range(10):
            cand = xy - alpha[..., None] * step
            c = distort(cand, dist)
            c_err = c.xy_dist - target
            c_res = np.linalg.norm(c_err, axis=-1)
            better = c.valid & np.isfinite(c_res) & (c_res < res)
            need = active & ~better & (alpha > 1e-3)
            if not np.any(need):
                break
            alpha = np.where(need, alpha / 2, alpha)
        accept = active & better
        xy = np.where(accept[..., None], cand, xy)
        err = np.where(accept[..., None], c_err, err)
        res = np.where(accept, c_res, res)
        if not np.any(accept):
            break
        cur = distort(xy, dist)
    converged = res <= tol
    valid = converged & distort(xy, dist).valid
    return UndistortResult(xy=xy, converged=converged, valid=valid, residual=res, iterations=iterations)
