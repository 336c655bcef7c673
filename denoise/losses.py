"""Differentiable image losses (torch): Charbonnier, gradient, chroma, total variation.

All functions take image batches ``[B, C, H, W]`` (float32 or float64, values
nominally in ``[0, 1]``), work on any device, and return a scalar tensor of the
input's dtype unless ``reduction="none"`` is asked for.

SSIM is `mvgeo.image_metrics.ssim`, the project's one SSIM (shared with the
splatting loss and the evaluation).
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from denoise.filters import gaussian_blur
from mvgeo.common.errors import ShapeError, check_shape

__all__ = [
    "charbonnier",
    "gaussian_blur",
    "gradient_loss",
    "image_gradients",
    "rgb_to_ycbcr",
    "chroma_loss",
    "total_variation",
    "low_frequency_loss",
    "neighbor2neighbor_loss",
]

Reduction = Literal["mean", "none"]


def _check_pair(x: Tensor, y: Tensor) -> None:
    check_shape(x, ["B", "C", "H", "W"], "x")
    if x.shape != y.shape:
        raise ShapeError(f"x and y must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}")


def _reduce(per_pixel: Tensor, reduction: Reduction) -> Tensor:
    """``mean``: scalar over everything; ``none``: one value per image, ``[B]``."""
    if reduction == "mean":
        return per_pixel.mean()
    if reduction == "none":
        return per_pixel.flatten(1).mean(1)
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


def charbonnier(x: Tensor, y: Tensor, *, eps: float = 1e-3, reduction: Reduction = "mean") -> Tensor:
    """Charbonnier (smooth L1) penalty ``mean(sqrt((x - y)^2 + eps^2))``.

    The classic form (Charbonnier et al. 1994; LapSRN): it equals `eps` when
    ``x == y`` and ``|x - y|`` far from zero, and is smooth at zero.

    Args:
        x, y: ``[B, C, H, W]``.
        eps: smoothing scale in intensity units.
        reduction: ``"mean"`` (scalar) or ``"none"`` (``[B]``).
    """
    _check_pair(x, y)
    return _reduce(torch.sqrt((x - y) ** 2 + eps * eps), reduction)


def image_gradients(x: Tensor) -> tuple[Tensor, Tensor]:
    """Forward differences along x (columns) and y (rows).

    Args:
        x: ``[B, C, H, W]``.

    Returns:
        ``(dx [B, C, H, W-1], dy [B, C, H-1, W])``.
    """
    check_shape(x, ["B", "C", "H", "W"], "x")
    return x[..., :, 1:] - x[..., :, :-1], x[..., 1:, :] - x[..., :-1, :]


def gradient_loss(x: Tensor, y: Tensor, *, reduction: Reduction = "mean") -> Tensor:
    """Gradient consistency: mean L1 distance between forward differences of `x` and `y`.

    ``0.5 * (mean|dx(x) - dx(y)| + mean|dy(x) - dy(y)|)``. Zero when `x` and `y`
    differ by a constant; insensitive to the low-frequency content.

    Args:
        x, y: ``[B, C, H, W]`` with ``H, W >= 2``.
    """
    _check_pair(x, y)
    if x.shape[-1] < 2 or x.shape[-2] < 2:
        raise ShapeError(f"gradient_loss needs H, W >= 2, got {tuple(x.shape)}")
    gxx, gxy = image_gradients(x)
    gyx, gyy = image_gradients(y)
    return 0.5 * (_reduce((gxx - gyx).abs(), reduction) + _reduce((gxy - gyy).abs(), reduction))


# ITU-R BT.601 full-range (JPEG) RGB -> YCbCr for values in [0, 1].
_YCBCR = (
    (0.299, 0.587, 0.114),
    (-0.168736, -0.331264, 0.5),
    (0.5, -0.418688, -0.081312),
)


def rgb_to_ycbcr(x: Tensor) -> Tensor:
    """RGB ``[B, 3, H, W]`` in ``[0, 1]`` -> YCbCr (BT.601 full range, JPEG) with Cb, Cr in ``[0, 1]``.

    ``Y = 0.299 R + 0.587 G + 0.114 B``; ``Cb, Cr`` are offset by 0.5, so a grey
    pixel has ``Cb = Cr = 0.5``. Matches ``skimage.color.rgb2ycbcr / 255`` up
    to scikit-image's studio-range scaling (which we do not use).
    """
    check_shape(x, ["B", 3, "H", "W"], "x")
    m = torch.tensor(_YCBCR, dtype=x.dtype, device=x.device)
    out = torch.einsum("oc,bchw->bohw", m, x)
    offset = torch.tensor([0.0, 0.5, 0.5], dtype=x.dtype, device=x.device).reshape(1, 3, 1, 1)
    return out + offset


def chroma_loss(x: Tensor, y: Tensor, *, eps: float = 1e-3, reduction: Reduction = "mean") -> Tensor:
    """Charbonnier distance between the chroma channels (Cb, Cr of YCbCr) of two RGB batches.

    Zero-ish (= `eps`) when the colours agree, whatever the luminance differences.

    Args:
        x, y: ``[B, 3, H, W]`` RGB.
    """
    _check_pair(x, y)
    return charbonnier(rgb_to_ycbcr(x)[:, 1:], rgb_to_ycbcr(y)[:, 1:], eps=eps, reduction=reduction)


def total_variation(x: Tensor, *, eps: float = 0.0, reduction: Reduction = "mean") -> Tensor:
    """Anisotropic total variation: ``mean|dx| + mean|dy|`` (forward differences).

    Args:
        x: ``[B, C, H, W]`` with ``H, W >= 2``.
        eps: if > 0, ``|d|`` is replaced by ``sqrt(d^2 + eps^2)`` (smooth at 0).
    """
    check_shape(x, ["B", "C", "H", "W"], "x")
    if x.shape[-1] < 2 or x.shape[-2] < 2:
        raise ShapeError(f"total_variation needs H, W >= 2, got {tuple(x.shape)}")
    dx, dy = image_gradients(x)
    if eps > 0:
        ax, ay = torch.sqrt(dx * dx + eps * eps), torch.sqrt(dy * dy + eps * eps)
    else:
        ax, ay = dx.abs(), dy.abs()
    return _reduce(ax, reduction) + _reduce(ay, reduction)


def low_frequency_loss(x: Tensor, y: Tensor, *, sigma: float = 2.0, eps: float = 1e-3,
                       reduction: Reduction = "mean") -> Tensor:
    """Charbonnier between Gaussian-smoothed `x` and `y` (the round-2 low-frequency term).

    Args:
        x, y: ``[B, C, H, W]``.
        sigma: blur standard deviation in pixels (``reflect`` border).
    """
    _check_pair(x, y)
    return charbonnier(gaussian_blur(x, sigma=sigma), gaussian_blur(y, sigma=sigma), eps=eps, reduction=reduction)


def neighbor2neighbor_loss(pred1: Tensor, target2: Tensor, full1: Tensor, full2: Tensor, *, gamma: float = 2.0,
                           reduction: Reduction = "mean") -> Tensor:
    """Neighbor2Neighbor loss (Huang et al. 2021, eq. 8), mean over pixels and channels.

    ``|pred1 - target2|^2 + gamma * |pred1 - target2 - (full1 - full2)|^2`` with
    ``pred1 = f(g1(y))``, ``target2 = g2(y)`` and ``full1, full2 = g1(f(y)), g2(f(y))``:
    the network's output on the whole image, sub-sampled with the same pixel choice and
    detached here (the paper's stop-gradient). Zero when the prediction equals the target
    and ``full1 == full2``.

    Args:
        pred1, target2, full1, full2: ``[B, C, h, w]`` (see `denoise.neighbor2neighbor`).
        gamma: weight of the regulariser (>= 0).
        reduction: ``"mean"`` (scalar) or ``"none"`` (``[B]``).
    """
    for t in (target2, full1, full2):
        _check_pair(pred1, t)
    if gamma < 0:
        raise ValueError(f"gamma must be >= 0, got {gamma}")
    diff = pred1 - target2
    reg = diff - (full1 - full2).detach()
    return _reduce(diff * diff + gamma * reg * reg, reduction)
