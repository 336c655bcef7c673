"""Separable Gaussian filtering of image batches (torch, differentiable): the primitives shared
by the image metrics (`mvgeo.image_metrics`, SSIM) and the denoiser (`denoise.filters`).

Border handling is explicit because it decides whether we match
`scipy.ndimage`/scikit-image: ``"valid"`` returns only pixels whose window lies
inside the image, ``"reflect"`` extends the image by half-sample symmetric
mirroring (``d c b a | a b c d | d c b a``; scipy's ``mode="reflect"``,
numpy's ``"symmetric"``; torch's own ``"reflect"`` pad is the whole-sample
mirror and is *not* used).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from mvgeo.common.errors import ShapeError, check_shape

__all__ = ["Border", "gaussian_kernel1d", "pad_symmetric", "separable_filter"]

Border = Literal["valid", "reflect"]


def gaussian_kernel1d(window_size: int, sigma: float, *, dtype: torch.dtype = torch.float32,
                      device: torch.device | str | None = None) -> Tensor:
    """Normalised 1-D Gaussian taps ``exp(-x^2 / (2 sigma^2))`` for ``x = -r..r``.

    Args:
        window_size: odd number of taps, ``2 r + 1``.
        sigma: standard deviation in pixels, > 0.

    Returns:
        kernel: ``(window_size,)``, sums to 1.
    """
    if window_size < 1 or window_size % 2 != 1:
        raise ValueError(f"window_size must be a positive odd integer, got {window_size}")
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    r = window_size // 2
    x = torch.arange(-r, r + 1, dtype=dtype, device=device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def pad_symmetric(x: Tensor, r: int) -> Tensor:
    """Half-sample symmetric padding of the last two dims by `r` (scipy ``reflect``).

    Works for any `r` (the image is mirrored repeatedly if `r` exceeds its size).

    Args:
        x: ``[B, C, H, W]``.

    Returns:
        ``[B, C, H + 2r, W + 2r]``.
    """
    if r == 0:
        return x
    h, w = x.shape[-2:]
    rows = _symmetric_index(h, r, x.device)
    cols = _symmetric_index(w, r, x.device)
    return x.index_select(-2, rows).index_select(-1, cols)


def _symmetric_index(n: int, r: int, device: torch.device) -> Tensor:
    idx = torch.arange(-r, n + r, device=device)
    period = 2 * n
    idx = torch.remainder(idx, period)
    return torch.where(idx >= n, period - 1 - idx, idx)


def separable_filter(x: Tensor, kernel: Tensor, *, border: Border = "reflect") -> Tensor:
    """Filter each channel with the outer product ``kernel ⊗ kernel`` (rows then columns).

    Args:
        x: ``[B, C, H, W]``.
        kernel: ``(K,)`` taps, K odd, same dtype/device as `x`.
        border: ``"reflect"`` (output ``[B, C, H, W]``) or ``"valid"``
            (output ``[B, C, H - K + 1, W - K + 1]``).
    """
    check_shape(x, ["B", "C", "H", "W"], "x")
    k = kernel.numel()
    r = k // 2
    c = x.shape[1]
    if border == "reflect":
        x = pad_symmetric(x, r)
    elif border != "valid":
        raise ValueError(f"border must be 'valid' or 'reflect', got {border!r}")
    if x.shape[-2] < k or x.shape[-1] < k:
        raise ShapeError(f"image {tuple(x.shape[-2:])} is smaller than the {k}x{k} window")
    kh = kernel.to(dtype=x.dtype, device=x.device).reshape(1, 1, 1, k).expand(c, 1, 1, k)
    kv = kernel.to(dtype=x.dtype, device=x.device).reshape(1, 1, k, 1).expand(c, 1, k, 1)
    x = F.conv2d(x, kh, groups=c)
    return F.conv2d(x, kv, groups=c)
