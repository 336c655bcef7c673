"""Differentiable torch twins of `mvgeo.transforms` (same names and conventions).

Conventions (docs/conventions.md): quaternions ``wxyz``; se(3) tangent
``[omega (3), v (3)]``; ``se3_exp`` returns ``(..., 4, 4)`` so a left-multiplied
pose correction reads ``cam_from_world_new = se3_exp(delta) @ cam_from_world``.

Every function takes arbitrary batch dims, keeps the input's dtype and device,
and has finite values *and gradients* at angle 0 (Taylor series behind a
"double where", so the unused branch never produces NaN/Inf gradients) and
near angle ``pi``. Float64 gradients are checked with
``torch.autograd.gradcheck`` in ``tests/mvgeo/test_transforms_torch.py``.
"""

from __future__ import annotations

import torch

from mvgeo.common.errors import ShapeError
from mvgeo.transforms import _C_SERIES, _D_SERIES, _SERIES_ANGLE

__all__ = ["skew", "R_from_quat", "quat_from_R", "so3_exp", "so3_log", "se3_exp", "se3_log"]


def _check_last(x: torch.Tensor, dims: tuple[int, ...], name: str) -> None:
    if not isinstance(x, torch.Tensor):
        raise ShapeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim < len(dims) or tuple(x.shape[x.ndim - len(dims):]) != dims:
        raise ShapeError(f"{name}: expected shape (..., {', '.join(map(str, dims))}), got {tuple(x.shape)}")


def _poly_t2(coeffs, theta2: torch.Tensor) -> torch.Tensor:
    out = torch.zeros_like(theta2)
    for c in coeffs[::-1]:
        out = out * theta2 + float(c)
    return out


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix. v: (..., 3) -> (..., 3, 3)."""
    _check_last(v, (3,), "v")
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def R_from_quat(q_wxyz: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from quaternions ``[w, x, y, z]`` (normalised here; either sign).

    The gradient is that of ``R(q / |q|)``, so unnormalised quaternions (as
    stored for Gaussians) are fine. A zero quaternion gives a finite but
    meaningless rotation (``|q|`` is clamped to 1e-12); keep quaternions away
    from zero in optimisers.

    Args:
        q_wxyz: (..., 4).

    Returns:
        (..., 3, 3), same dtype/device.
    """
    _check_last(q_wxyz, (4,), "q_wxyz")
    q = q_wxyz / q_wxyz.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def quat_from_R(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``[w, x, y, z]``, ``w >= 0``, from rotation matrices (Shepperd's method).

    Differentiable almost everywhere (the pivot choice is piecewise constant);
    square roots of the unused pivots are clamped so they cannot inject NaN
    gradients.

    Args:
        R: (..., 3, 3).

    Returns:
        (..., 4), same dtype/device.
    """
    _check_last(R, (3, 3), "R")
    m = R.reshape(R.shape[:-2] + (9,))
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.unbind(-1)
    tr = m00 + m11 + m22
    pivots = torch.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1)
    s = 2 * torch.sqrt(pivots.clamp_min(1e-12))  # 4 |q_k| for each candidate k
    d21, d02, d10 = m21 - m12, m02 - m20, m10 - m01
    s01, s02, s12 = m01 + m10, m02 + m20, m12 + m21
    s0, s1, s2, s3 = s.unbind(-1)
    cand = torch.stack(
        [
            torch.stack([0.25 * s0, d21 / s0, d02 / s0, d10 / s0], -1),
            torch.stack([d21 / s1, 0.25 * s1, s01 / s1, s02 / s1], -1),
            torch.stack([d02 / s2, s01 / s2, 0.25 * s2, s12 / s2], -1),
            torch.stack([d10 / s3, s02 / s3, s12 / s3, 0.25 * s3], -1),
        ],
        dim=-2,
    )
    k = pivots.argmax(dim=-1)
    idx = k[..., None, None].expand(k.shape + (1, 4))
    q = torch.gather(cand, -2, idx).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def _abc(theta2: torch.Tensor):
    """A = sin t/t, B = (1-cos t)/t^2, C = (t - sin t)/t^3 with safe series (values and gradients)."""
    zero = theta2 < 1e-8  # t < 1e-4: series error O(t^6) < 1e-24
    t2 = torch.where(zero, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    A = torch.where(zero, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    B = torch.where(zero, 0.5 - theta2 / 24 + theta2**2 / 720, 2 * (torch.sin(t / 2) / t) ** 2)
    series = theta2 < _SERIES_ANGLE**2
    t2c = torch.where(series, torch.ones_like(theta2), theta2)
    tc = torch.sqrt(t2c)
    C = torch.where(series, _poly_t2(_C_SERIES, theta2), (tc - torch.sin(tc)) / (t2c * tc))
    return A, B, C


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues: omega (..., 3) radians -> R (..., 3, 3)."""
    _check_last(omega, (3,), "omega")
    theta2 = (omega * omega).sum(-1)
    A, B, _ = _abc(theta2)
    K = skew(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye + A[..., None, None] * K + B[..., None, None] * (K @ K)


def _axis_angle_from_quat(q: torch.Tensor) -> torch.Tensor:
    w = q[..., 0]
    v = q[..., 1:]
    n2 = (v * v).sum(-1)
    small = n2 < 1e-8
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    w_safe = torch.where(small, w, torch.ones_like(w))
    x2 = n2 / (w_safe * w_safe)
    factor = torch.where(small, (2 / w_safe) * (1 - x2 / 3 + x2 * x2 / 5), 2 * torch.atan2(n, w) / n)
    return v * factor[..., None]


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector (angle in [0, pi]) of R (..., 3, 3) -> (..., 3), via the w>=0 quaternion."""
    return _axis_angle_from_quat(quat_from_R(R))


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Exponential map of se(3): xi (..., 6) ``[omega, v]`` -> (..., 4, 4) homogeneous."""
    _check_last(xi, (6,), "xi")
    omega, v = xi[..., :3], xi[..., 3:]
    theta2 = (omega * omega).sum(-1)
    A, B, C = _abc(theta2)
    K = skew(omega)
    K2 = K @ K
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    R = eye + A[..., None, None] * K + B[..., None, None] * K2
    V = eye + B[..., None, None] * K + C[..., None, None] * K2
    t = (V @ v[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], dim=-1)
    bottom = torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Logarithm of rigid transforms (..., 3, 4) or (..., 4, 4) -> (..., 6) ``[omega, v]``."""
    if not isinstance(T, torch.Tensor) or T.ndim < 2 or T.shape[-1] != 4 or T.shape[-2] not in (3, 4):
        raise ShapeError(f"T: expected shape (..., 3, 4) or (..., 4, 4), got {tuple(getattr(T, 'shape', ()))}")
    R, t = T[..., :3, :3], T[..., :3, 3]
    omega = so3_log(R)
    theta2 = (omega * omega).sum(-1)
    series = theta2 < _SERIES_ANGLE**2
    t2 = torch.where(series, torch.ones_like(theta2), theta2)
    half = torch.sqrt(t2) / 2
    D = torch.where(series, _poly_t2(_D_SERIES, theta2), (1 - half * torch.cos(half) / torch.sin(half)) / t2)
    K = skew(omega)
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    V_inv = eye - 0.5 * K + D[..., None, None] * (K @ K)
    v = (V_inv @ t[..., None])[..., 0]
    return torch.cat([omega, v], dim=-1)
