"""Rotations, rigid and similarity transforms (numpy, float64).

Conventions (docs/conventions.md): quaternions are ``wxyz`` and canonicalised
to ``w >= 0``; axis-angle ``omega`` has angle ``|omega|`` in radians in
``[0, pi]``; transforms are named ``B_from_A`` and compose right to left.

Representation of transforms in this module: **matrices**. A rigid transform
is ``(..., 3, 4)`` ``[R | t]`` or ``(..., 4, 4)`` homogeneous; a similarity is
the same with ``s * R`` in the rotation block. ``compose``/``invert``/``apply``
accept either layout and return the layout they were given (``compose`` of a
3x4 with anything returns 3x4 only if both are 3x4). ``Rt_from_matrix`` and
``matrix_from_Rt`` convert to and from ``(R, t)`` pairs.

Tangent spaces: se(3) ``xi = [omega (3), v (3)]``; sim(3)
``[omega (3), v (3), log_s (1)]``. ``exp`` maps a tangent vector to a
transform ``T`` so that a left perturbation reads ``exp(delta) @ T``.

Numerical notes: every ``sin(x)/x``-type coefficient switches to its Taylor
series below a small angle, so exp/log are accurate (relative error ~1e-16)
at and near angle 0; the logarithm goes through the quaternion with
``atan2``, which is well conditioned up to and including angle ``pi``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mvgeo.common.errors import DegenerateGeometryError, ShapeError, check_shape

__all__ = [
    "R_from_quat",
    "quat_from_R",
    "R_from_axis_angle",
    "axis_angle_from_R",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "skew",
    "skew_unchecked",
    "project_to_so3",
    "se3_exp",
    "se3_log",
    "sim3_exp",
    "sim3_log",
    "matrix_from_Rt",
    "Rt_from_matrix",
    "compose",
    "invert",
    "apply",
    "camera_centre",
    "Sim3",
    "umeyama",
    "average_rotations_chordal",
]

# Below this angle (radians) the trigonometric coefficients use Taylor series.
# Truncation error of the series used is O(theta^6) ~ 1e-24 at 1e-4: far below
# float64 epsilon, while the closed forms lose ~eps/theta^2 ~ 1e-8 there.
_SMALL_ANGLE = 1e-4


def _as_f64(x, name: str) -> np.ndarray:
    arr = np.asarray(x)
    if not np.issubdtype(arr.dtype, np.number):
        raise ShapeError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


def skew(v) -> np.ndarray:
    """Cross-product matrix ``[v]_x`` with ``[v]_x @ w == cross(v, w)``.

    Args:
        v: (..., 3).

    Returns:
        (..., 3, 3) float64.
    """
    v = _as_f64(v, "v")
    check_shape(v, ["*", 3], "v")
    return skew_unchecked(v)


def skew_unchecked(v: np.ndarray) -> np.ndarray:
    """`skew` of a float64 (..., 3) array without its input checks, for inner loops (a two-view refinement's
    Jacobian, the bundle adjustment's)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


# ----------------------------------------------------------------------------- quaternions


def R_from_quat(q_wxyz) -> np.ndarray:
    """Rotation matrix from a quaternion ``[w, x, y, z]`` (either sign; normalised here).

    Args:
        q_wxyz: (..., 4), any non-zero norm.

    Returns:
        (..., 3, 3) float64 rotation matrices.

    Raises:
        DegenerateGeometryError: a quaternion has (near-)zero norm.
    """
    q = _as_f64(q_wxyz, "q_wxyz")
    check_shape(q, ["*", 4], "q_wxyz")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(norm < 1e-12):
        raise DegenerateGeometryError("R_from_quat: quaternion with zero norm or non-finite entries")
    w, x, y, z = np.moveaxis(q / norm, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quat_from_R(R) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` with ``w >= 0`` from a rotation matrix.

    Shepperd's method: of the four algebraically equivalent formulas, use the
    one whose pivot (``4 q_k^2``) is largest, so no division by a small number
    happens near angle ``pi`` (where ``w -> 0``). Slightly non-orthonormal
    input gives the quaternion of a nearby rotation (output is normalised).

    Args:
        R: (..., 3, 3).

    Returns:
        (..., 4) float64, unit norm, ``w >= 0``. At exactly angle ``pi``
        (``w == 0``) the sign is made deterministic: the first non-zero of
        ``x, y, z`` is positive.
    """
    R = _as_f64(R, "R")
    check_shape(R, ["*", 3, 3], "R")
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # Pivots 4*w^2, 4*x^2, 4*y^2, 4*z^2 (up to the common factor).
    pivots = np.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1)
    k = np.argmax(pivots, axis=-1)
    s = np.sqrt(np.maximum(np.take_along_axis(pivots, k[..., None], -1)[..., 0], 1e-300)) * 2.0  # 4*|q_k|
    d21 = R[..., 2, 1] - R[..., 1, 2]
    d02 = R[..., 0, 2] - R[..., 2, 0]
    d10 = R[..., 1, 0] - R[..., 0, 1]
    s01 = R[..., 0, 1] + R[..., 1, 0]
    s02 = R[..., 0, 2] + R[..., 2, 0]
    s12 = R[..., 1, 2] + R[..., 2, 1]
    cand = np.stack(
        [
            np.stack([0.25 * s, d21 / s, d02 / s, d10 / s], -1),
            np.stack([d21 / s, 0.25 * s, s01 / s, s02 / s], -1),
            np.stack([d02 / s, s01 / s, 0.25 * s, s12 / s], -1),
            np.stack([d10 / s, s02 / s, s12 / s, 0.25 * s], -1),
        ],
        axis=-2,
    )
    q = np.take_along_axis(cand, k[..., None, None], -2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return _canonical_quat(q)


def _canonical_quat(q: np.ndarray) -> np.ndarray:
    """Flip to ``w > 0``; for ``w == 0`` make the first non-zero of x, y, z positive."""
    sign = np.sign(q[..., 0])
    for i in (1, 2, 3):
        sign = np.where(sign == 0, np.sign(q[..., i]), sign)
    sign = np.where(sign == 0, 1.0, sign)
    return q * sign[..., None]


# ----------------------------------------------------------------------------- SO(3)


# Taylor coefficients (in powers of t^2) of C(t) = (t - sin t) / t^3 and of
# D(t) = (1 - (t/2) cot(t/2)) / t^2 = sum_n |B_2n| t^(2n-2) / (2n)!  (Bernoulli numbers).
_C_SERIES = np.array([(-1.0) ** k / np.prod(np.arange(1, 2 * k + 4, dtype=np.float64)) for k in range(8)])
_D_SERIES = np.array(
    [1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160, 691 / 2730 / 479001600,
     7 / 6 / 87178291200, 3617 / 510 / 20922789888000]
)
# The closed forms of C and D cancel catastrophically (relative error ~ eps / t^2);
# below this angle the series (8 terms, next term < 1e-17 relative at t = 0.5) is used.
_SERIES_ANGLE = 0.5
_C_SERIES_FLOATS = tuple(float(c) for c in _C_SERIES)


def _poly_t2(coeffs: np.ndarray, theta2: np.ndarray) -> np.ndarray:
    out = np.zeros_like(theta2)
    for c in coeffs[::-1]:
        out = out * theta2 + c
    return out


def _so3_coeffs(theta2: np.ndarray):
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, accurate for all t in [0, pi].

    A and B are written without cancellation (B = 2 sin^2(t/2) / t^2); C uses its series below 0.5.
    """
    zero = theta2 < _SMALL_ANGLE**2
    t2 = np.where(zero, 1.0, theta2)
    t = np.sqrt(t2)
    A = np.where(zero, 1 - theta2 / 6 + theta2**2 / 120, np.sin(t) / t)
    B = np.where(zero, 0.5 - theta2 / 24 + theta2**2 / 720, 2 * (np.sin(t / 2) / t) ** 2)
    series = theta2 < _SERIES_ANGLE**2
    t2c = np.where(series, 1.0, theta2)
    tc = np.sqrt(t2c)
    C = np.where(series, _poly_t2(_C_SERIES, theta2), (tc - np.sin(tc)) / (t2c * tc))
    return A, B, C


def so3_exp_and_left_jacobian(omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(so3_exp(omega), so3_left_jacobian(omega))`` of one rotation vector, sharing one evaluation of
    the coefficients in scalar arithmetic: the same formulas as `R_from_axis_angle` and
    `so3_left_jacobian` (the tests compare them) without their per-call array checks, for inner loops
    over one small rotation (a two-view refinement's Jacobian).

    Args:
        omega: (3,) rotation vector, radians.

    Returns:
        R (3, 3), J_l (3, 3), float64.
    """
    w = np.asarray(omega, np.float64)
    x, y, z = float(w[0]), float(w[1]), float(w[2])
    t2 = x * x + y * y + z * z
    t = math.sqrt(t2)
    if t2 < _SMALL_ANGLE**2:
        A, B = 1 - t2 / 6 + t2 * t2 / 120, 0.5 - t2 / 24 + t2 * t2 / 720
    else:
        A, B = math.sin(t) / t, 2 * (math.sin(t / 2) / t) ** 2
    if t2 < _SERIES_ANGLE**2:
        C = 0.0
        for c in _C_SERIES_FLOATS[::-1]:
            C = C * t2 + c
    else:
        C = (t - math.sin(t)) / (t2 * t)
    K = skew_unchecked(w)
    K2 = K @ K
    eye = np.eye(3)
    return eye + A * K + B * K2, eye + B * K + C * K2


def R_from_axis_angle(omega) -> np.ndarray:
    """Rodrigues' formula: rotation by angle ``|omega|`` about ``omega / |omega|``.

    Args:
        omega: (..., 3) rotation vectors, radians (any length; angles > pi wrap).

    Returns:
        (..., 3, 3) float64.
    """
    omega = _as_f64(omega, "omega")
    check_shape(omega, ["*", 3], "omega")
    theta2 = np.sum(omega * omega, axis=-1)
    A, B, _ = _so3_coeffs(theta2)
    K = skew(omega)
    return np.eye(3) + A[..., None, None] * K + B[..., None, None] * (K @ K)


def so3_left_jacobian(omega) -> np.ndarray:
    """Left Jacobian of SO(3): ``exp(omega + d) = exp([J_l(omega) d]_x) exp(omega)`` to first order in ``d``;
    ``J_l = I + B K + C K^2`` with `_so3_coeffs` (``K = [omega]_x``), the block V of `se3_exp`.

    Args:
        omega: (..., 3) rotation vectors, radians.

    Returns:
        (..., 3, 3) float64.
    """
    omega = _as_f64(omega, "omega")
    check_shape(omega, ["*", 3], "omega")
    _, B, C = _so3_coeffs(np.sum(omega * omega, axis=-1))
    K = skew(omega)
    return np.eye(3) + B[..., None, None] * K + C[..., None, None] * (K @ K)


def axis_angle_from_R(R) -> np.ndarray:
    """Rotation vector ``omega`` (angle in ``[0, pi]``) of a rotation matrix.

    Computed via the canonical quaternion ``(w >= 0, v)``:
    ``omega = 2 atan2(|v|, w) v / |v|``, with the series
    ``2/w (1 - n^2/(3 w^2) + n^4/(5 w^4))`` for ``n = |v|`` small. This is
    accurate near 0 (no ``arccos`` of a number near 1) and near ``pi``. At
    exactly ``pi`` the sign of ``omega`` is the quaternion's canonical sign
    (both signs are the same rotation).

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) float64.
    """
    q = quat_from_R(R)
    return _axis_angle_from_quat(q)


def _axis_angle_from_quat(q: np.ndarray) -> np.ndarray:
    w = q[..., 0]
    v = q[..., 1:]
    n2 = np.sum(v * v, axis=-1)
    n = np.sqrt(n2)
    small = n < 1e-4  # then w > 0.99999999; series error ~ n^6 < 1e-24
    w_safe = np.where(small, w, 1.0)
    n_safe = np.where(small, 1.0, n)
    x2 = n2 / (w_safe * w_safe)
    factor = np.where(small, (2 / w_safe) * (1 - x2 / 3 + x2 * x2 / 5), 2 * np.arctan2(n, w) / n_safe)
    return v * factor[..., None]


so3_exp = R_from_axis_angle
so3_log = axis_angle_from_R


def project_to_so3(M) -> np.ndarray:
    """Closest rotation (Frobenius norm) to each 3x3 matrix, via SVD with det fix.

    Args:
        M: (..., 3, 3).

    Returns:
        (..., 3, 3) float64 with det +1.
    """
    M = _as_f64(M, "M")
    check_shape(M, ["*", 3, 3], "M")
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vt


# ----------------------------------------------------------------------------- SE(3) / Sim(3)


def se3_exp(xi) -> np.ndarray:
    """Exponential map of se(3), tangent order ``[omega, v]``.

    ``exp(xi) = [[R, V v], [0, 1]]`` with ``R = so3_exp(omega)`` and
    ``V = I + B K + C K^2`` (``K = [omega]_x``).

    Args:
        xi: (..., 6).

    Returns:
        (..., 4, 4) float64 homogeneous transforms.
    """
    xi = _as_f64(xi, "xi")
    check_shape(xi, ["*", 6], "xi")
    omega, v = xi[..., :3], xi[..., 3:]
    theta2 = np.sum(omega * omega, axis=-1)
    A, B, C = _so3_coeffs(theta2)
    K = skew(omega)
    K2 = K @ K
    eye = np.eye(3)
    R = eye + A[..., None, None] * K + B[..., None, None] * K2
    V = eye + B[..., None, None] * K + C[..., None, None] * K2
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = (V @ v[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def _V_inv(omega: np.ndarray) -> np.ndarray:
    """Inverse of the SE(3) left Jacobian block V, ``I - K/2 + D K^2``."""
    theta2 = np.sum(omega * omega, axis=-1)
    series = theta2 < _SERIES_ANGLE**2
    t2 = np.where(series, 1.0, theta2)
    half = np.sqrt(t2) / 2
    # D = (1 - (t/2) cot(t/2)) / t^2; closed form valid up to t = pi (tan(pi/2) -> cot 0 fine).
    D = np.where(series, _poly_t2(_D_SERIES, theta2), (1 - half * np.cos(half) / np.sin(half)) / t2)
    K = skew(omega)
    return np.eye(3) - 0.5 * K + D[..., None, None] * (K @ K)


def se3_log(T) -> np.ndarray:
    """Logarithm of a rigid transform, ``[omega, v]``; inverse of `se3_exp` for angle < pi.

    Args:
        T: (..., 3, 4) or (..., 4, 4).

    Returns:
        (..., 6) float64.
    """
    R, t = Rt_from_matrix(T)
    omega = axis_angle_from_R(R)
    v = (_V_inv(omega) @ t[..., None])[..., 0]
    return np.concatenate([omega, v], axis=-1)


def _sim3_W(omega: np.ndarray, log_s: np.ndarray) -> np.ndarray:
    """W with t = W v for sim(3): W = integral_0^1 exp(a log_s) exp(a K) da (closed form + series)."""
    # Evaluated by Gauss-Legendre quadrature (16 nodes): the integrand is entire and
    # smooth on [0, 1], so quadrature is exact to float64 for |omega| <= pi and
    # |log_s| <~ 5; no special cases for (theta, log_s) near 0 are needed.
    nodes, weights = np.polynomial.legendre.leggauss(16)
    a = 0.5 * (nodes + 1.0)
    wts = 0.5 * weights
    W = np.zeros(omega.shape[:-1] + (3, 3))
    for ai, wi in zip(a, wts, strict=False):
        W = W + wi * np.exp(ai * log_s)[..., None, None] * R_from_axis_angle(ai * omega)
    return W


def sim3_exp(xi) -> np.ndarray:
    """Exponential map of sim(3), tangent order ``[omega, v, log_s]``.

    Returns ``[[s R, W v], [0, 1]]`` with ``s = exp(log_s)``,
    ``W = int_0^1 s^a exp(a [omega]_x) da``.

    Args:
        xi: (..., 7). ``|log_s|`` up to ~5 is exact to float64 precision.

    Returns:
        (..., 4, 4) float64.
    """
    xi = _as_f64(xi, "xi")
    check_shape(xi, ["*", 7], "xi")
    omega, v, log_s = xi[..., :3], xi[..., 3:6], xi[..., 6]
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = np.exp(log_s)[..., None, None] * R_from_axis_angle(omega)
    T[..., :3, 3] = (_sim3_W(omega, log_s) @ v[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def sim3_log(T) -> np.ndarray:
    """Logarithm of a similarity ``[[s R, t], [0, 1]]``, returns ``[omega, v, log_s]``.

    Args:
        T: (..., 3, 4) or (..., 4, 4) with ``det(s R) > 0``.

    Returns:
        (..., 7) float64.
    """
    A, t = Rt_from_matrix(T)
    det = np.linalg.det(A)
    if np.any(det <= 0):
        raise DegenerateGeometryError("sim3_log: the linear block has det <= 0 (not a similarity)")
    s = np.cbrt(det)
    R = A / s[..., None, None]
    omega = axis_angle_from_R(R)
    log_s = np.log(s)
    v = np.linalg.solve(_sim3_W(omega, log_s), t[..., None])[..., 0]
    return np.concatenate([omega, v, log_s[..., None]], axis=-1)


# ----------------------------------------------------------------------------- matrices


def matrix_from_Rt(R, t, *, homogeneous: bool = True) -> np.ndarray:
    """Stack ``(R, t)`` into ``(..., 4, 4)`` (default) or ``(..., 3, 4)``.

    Args:
        R: (..., 3, 3) (or ``s R`` for a similarity).
        t: (..., 3).
        homogeneous: return 4x4 if True else 3x4.
    """
    R = _as_f64(R, "R")
    t = _as_f64(t, "t")
    check_shape(R, ["*", 3, 3], "R")
    check_shape(t, ["*", 3], "t")
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    out = np.zeros(batch + ((4, 4) if homogeneous else (3, 4)))
    out[..., :3, :3] = R
    out[..., :3, 3] = t
    if homogeneous:
        out[..., 3, 3] = 1.0
    return out


def Rt_from_matrix(T) -> tuple[np.ndarray, np.ndarray]:
    """Split ``(..., 3, 4)`` or ``(..., 4, 4)`` into ``R (..., 3, 3)`` and ``t (..., 3)`` (copies)."""
    T = _as_f64(T, "T")
    if T.ndim < 2 or T.shape[-1] != 4 or T.shape[-2] not in (3, 4):
        raise ShapeError(f"T: expected shape (..., 3, 4) or (..., 4, 4), got {T.shape}")
    return T[..., :3, :3].copy(), T[..., :3, 3].copy()


def _check_T(T, name: str) -> np.ndarray:
    T = _as_f64(T, name)
    if T.ndim < 2 or T.shape[-1] != 4 or T.shape[-2] not in (3, 4):
        raise ShapeError(f"{name}: expected shape (..., 3, 4) or (..., 4, 4), got {T.shape}")
    return T


def compose(a_from_b, b_from_c) -> np.ndarray:
    """``a_from_c = a_from_b @ b_from_c`` for rigid or similarity transforms.

    Args:
        a_from_b: (..., 3, 4) or (..., 4, 4).
        b_from_c: (..., 3, 4) or (..., 4, 4); batch dims broadcast.

    Returns:
        (..., 3, 4) if both inputs are 3x4, else (..., 4, 4).
    """
    A = _check_T(a_from_b, "a_from_b")
    B = _check_T(b_from_c, "b_from_c")
    R = A[..., :3, :3] @ B[..., :3, :3]
    t = (A[..., :3, :3] @ B[..., :3, 3:4])[..., 0] + A[..., :3, 3]
    return matrix_from_Rt(R, t, homogeneous=not (A.shape[-2] == 3 and B.shape[-2] == 3))


def invert(b_from_a) -> np.ndarray:
    """``a_from_b`` for a rigid or similarity transform (same layout as the input).

    The linear block ``M = s R`` is inverted as ``M^T / s^2`` with
    ``s = cbrt(det M)``, exact for rotations and similarities (not for general
    affine maps, which this project does not use).

    Args:
        b_from_a: (..., 3, 4) or (..., 4, 4).
    """
    T = _check_T(b_from_a, "b_from_a")
    M, t = T[..., :3, :3], T[..., :3, 3]
    s2 = np.cbrt(np.linalg.det(M)) ** 2
    if np.any(~(s2 > 0)):
        raise DegenerateGeometryError("invert: transform with a singular linear block")
    Minv = np.swapaxes(M, -1, -2) / s2[..., None, None]
    return matrix_from_Rt(Minv, -(Minv @ t[..., None])[..., 0], homogeneous=T.shape[-2] == 4)


def apply(b_from_a, points_a) -> np.ndarray:
    """Map points: ``x_b = M @ x_a + t``.

    Args:
        b_from_a: (..., 3, 4) or (..., 4, 4).
        points_a: (..., N, 3); batch dims broadcast with those of the transform.

    Returns:
        (..., N, 3) float64.
    """
    T = _check_T(b_from_a, "b_from_a")
    p = _as_f64(points_a, "points_a")
    check_shape(p, ["*", "N", 3], "points_a")
    return p @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def camera_centre(cam_from_world) -> np.ndarray:
    """Camera centre in world coordinates, ``C = -R^T t``.

    Args:
        cam_from_world: (..., 3, 4) or (..., 4, 4) rigid transforms.

    Returns:
        (..., 3) float64.
    """
    R, t = Rt_from_matrix(cam_from_world)
    return -(np.swapaxes(R, -1, -2) @ t[..., None])[..., 0]


# ----------------------------------------------------------------------------- Umeyama


@dataclass(frozen=True)
class Sim3:
    """A similarity ``x_dst = scale * R @ x_src + t`` (``dst_from_src``).

    Attributes:
        scale: positive scalar (1.0 for a rigid fit).
        R: (3, 3) rotation.
        t: (3,) translation.
        rmse: root-mean-square residual of the fit, in ``dst`` units (weighted if weights were given).
        well_posed: False when the rotation is not unique: all source points
            (or all destination points) lie on a line, so any rotation about
            that line fits equally well. The returned R is then one valid
            minimiser, not *the* answer.
    """

    scale: float
    R: np.ndarray
    t: np.ndarray
    rmse: float = 0.0
    well_posed: bool = True

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous ``[[s R, t], [0, 1]]``."""
        return matrix_from_Rt(self.scale * self.R, self.t)

    def apply(self, points) -> np.ndarray:
        """Map (..., 3) points from src to dst."""
        p = _as_f64(points, "points")
        check_shape(p, ["*", 3], "points")
        return self.scale * p @ self.R.T + self.t


def umeyama(src, dst, *, weights=None, with_scale: bool = True) -> Sim3:
    """Least-squares similarity (or rigid) transform mapping ``src`` onto ``dst``.

    Minimises ``sum_i w_i |dst_i - (s R src_i + t)|^2`` (Umeyama 1991, with
    weights); ``R`` is a proper rotation (reflection fixed by the sign of the
    smallest singular value).

    Args:
        src: (N, 3) points.
        dst: (N, 3) corresponding points.
        weights: (N,) non-negative, optional (default all ones).
        with_scale: fit ``s`` (Sim(3)); else ``s = 1`` (SE(3), Kabsch).

    Returns:
        `Sim3` with ``well_posed=False`` for collinear configurations.

    Raises:
        ShapeError: mismatched shapes.
        DegenerateGeometryError: fewer than 2 points with positive weight, or
            all (weighted) source points coincide (scale and rotation undefined).
    """
    src = _as_f64(src, "src")
    dst = _as_f64(dst, "dst")
    check_shape(src, ["N", 3], "src")
    check_shape(dst, [src.shape[0], 3], "dst")
    n = src.shape[0]
    w = np.ones(n) if weights is None else _as_f64(weights, "weights")
    check_shape(w, [n], "weights")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst)) and np.all(np.isfinite(w))):
        raise DegenerateGeometryError("umeyama: non-finite input points or weights")
    if np.any(w < 0):
        raise DegenerateGeometryError("umeyama: negative weights")
    if np.count_nonzero(w > 0) < 2:
        raise DegenerateGeometryError("umeyama: need at least 2 points with positive weight")
    wn = w / w.sum()
    mu_s = wn @ src
    mu_d = wn @ dst
    xs = src - mu_s
    xd = dst - mu_d
    var_s = float(wn @ np.sum(xs * xs, axis=1))
    scale_ref = max(float(np.max(np.abs(src))), float(np.max(np.abs(dst))), 1e-300)
    if var_s <= (1e-12 * scale_ref) ** 2:
        raise DegenerateGeometryError(
            "umeyama: all source points coincide; scale and rotation are undefined"
        )
    cov = (xd * wn[:, None]).T @ xs  # (3, 3) = sum w dst src^T
    U, S, Vt = np.linalg.svd(cov)
    d = 1.0 if np.linalg.det(U) * np.linalg.det(Vt) >= 0 else -1.0
    D = np.array([1.0, 1.0, d])
    R = (U * D) @ Vt
    scale = float((S * D).sum() / var_s) if with_scale else 1.0
    if with_scale and scale <= 0:
        # Only when dst variance is zero (all dst coincide) together with a reflection fix.
        scale = 0.0
    t = mu_d - scale * R @ mu_s
    resid = dst - (scale * src @ R.T + t)
    rmse = float(np.sqrt(wn @ np.sum(resid * resid, axis=1)))
    # Rotation is unique iff rank(cov) >= 2 (S[1] > 0 relative to S[0]).
    well_posed = bool(S[0] > 0 and S[1] > 1e-9 * S[0])
    return Sim3(scale=scale, R=R, t=t, rmse=rmse, well_posed=well_posed)


def average_rotations_chordal(Rs, *, weights=None) -> np.ndarray:
    """Chordal L2 mean: the rotation closest in Frobenius norm to ``sum_i w_i R_i``.

    Args:
        Rs: (N, 3, 3) rotations.
        weights: (N,) non-negative, optional.

    Returns:
        (3, 3) float64.

    Raises:
        DegenerateGeometryError: empty input or weights summing to zero.
    """
    Rs = _as_f64(Rs, "Rs")
    check_shape(Rs, ["N", 3, 3], "Rs")
    n = Rs.shape[0]
    w = np.ones(n) if weights is None else _as_f64(weights, "weights")
    check_shape(w, [n], "weights")
    if n == 0 or not np.sum(w) > 0 or np.any(w < 0):
        raise DegenerateGeometryError("average_rotations_chordal: need >= 1 rotation with positive weight")
    return project_to_so3(np.einsum("n,nij->ij", w, Rs))
