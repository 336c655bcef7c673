"""The bias that clipping at 0 and 1 leaves in a denoiser's output, and its inverse.

A photo stores ``y = clip(x + n, 0, 1)``. Where ``x`` is within a few noise std of 0 (a black
background) or 1 (a blown highlight), the clipped noise no longer averages to zero:
``E[y] = f(x) > x`` near 0 and ``< x`` near 1. A denoiser trained on such photos with a
mean-square objective (N2V, R2R, Neighbor2Neighbor: their targets are clipped noisy pixels)
estimates ``E[y | context] = f(x)``, so a black background comes out grey: on the temple ring at
sigma 25/255 the background (about half of each photo) read 11/255 instead of 0-1/255 after R2R,
two thirds of the photos' remaining error.

For Gaussian noise of std ``s`` (a number or a per-pixel map), with ``a = -x / s`` and
``b = (1 - x) / s``::

    f(x) = x (Phi(b) - Phi(a)) + s (phi(a) - phi(b)) + (1 - Phi(b))

(the mean of a Gaussian clipped to ``[0, 1]``; Phi, phi: the standard normal cdf and density).
``f`` is increasing (``f'(x) = Phi(b) - Phi(a) > 0``), so `undo_clipping_bias` inverts it by
Newton's method, pixel by pixel, and clamps the result to ``[0, 1]``: the debiasing step of Foi's
"Clipped noisy images: heteroskedastic modeling and practical denoising" (Signal Processing 2009),
applied to the network's estimate. A side whose photo holds no clipped pixels (no exact 0, or no
exact 1) is left alone (`clipped_sides`): there the noise was not clipped and ``f`` would not apply.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["DARK_CLIPPED_BLUR_PX", "DARK_CLIPPED_MIN_LOCAL", "MIN_CLIPPED_FRACTION", "clipped_mean", "clipped_sides",
           "clipped_variance", "dark_clipped_fraction", "dark_clipped_mask", "undo_clipping_bias"]

#: A side of a photo counts as clipped when at least this fraction of its values sit exactly on it.
#: Unclipped noise puts no value exactly on 0 or 1 (8-bit: only where x is within half a level of it
#: and the noise lands there too); a black background at sigma 25/255 puts a third of the values on 0.
MIN_CLIPPED_FRACTION = 1e-3

NEWTON_ITERS = 30

#: `dark_clipped_fraction`: the neighbourhood (Gaussian std, px) whose share of values at 0 is read...
DARK_CLIPPED_BLUR_PX = 4.0
#: ... and the share above which a pixel lies in a dark clipped region. Over black (x = 0) half of the
#: values of Gaussian noise land on 0; at x = sigma 16 %, at x = 2 sigma 2 %.
DARK_CLIPPED_MIN_LOCAL = 0.4


def _phi(t: Tensor) -> Tensor:
    return torch.exp(-0.5 * t * t) * (1.0 / np.sqrt(2.0 * np.pi))


def _bounds(x: Tensor, sigma: Tensor, low: bool, high: bool) -> tuple[Tensor, Tensor]:
    inf = torch.full_like(x, float("inf"))
    a = -x / sigma if low else -inf
    b = (1.0 - x) / sigma if high else inf
    return a, b


def _mean_and_slope(x: Tensor, sigma: Tensor, low: bool, high: bool) -> tuple[Tensor, Tensor]:
    """``f(x)`` and ``f'(x) = Phi(b) - Phi(a)`` (`sigma` already a tensor)."""
    a, b = _bounds(x, sigma, low, high)
    cdf_a, cdf_b = torch.special.ndtr(a), torch.special.ndtr(b)
    return x * (cdf_b - cdf_a) + sigma * (_phi(a) - _phi(b)) + (1.0 - cdf_b), cdf_b - cdf_a


def clipped_mean(x: Tensor, sigma: float | Tensor, *, low: bool = True, high: bool = True) -> Tensor:
    """``E[clip(x + n, 0, 1)]`` for ``n ~ N(0, sigma^2)`` (each side clipped only if `low` / `high`).

    Args:
        x: clean values, any shape (float).
        sigma: noise std, a number or a tensor broadcastable to `x` (``> 0``).
    """
    return _mean_and_slope(x, torch.as_tensor(sigma, dtype=x.dtype, device=x.device).clamp_min(1e-6), low, high)[0]


def clipped_variance(x: Tensor, sigma: float | Tensor, *, low: bool = True, high: bool = True) -> Tensor:
    """``Var[clip(x + n, 0, 1)]`` for ``n ~ N(0, sigma^2)`` (each side clipped only if `low` / `high`).

    With ``a = -x / s``, ``b = (1 - x) / s``, the second moment of the clipped value is
    ``(x^2 + s^2) (Phi(b) - Phi(a)) + 2 x s (phi(a) - phi(b)) + s^2 (a phi(a) - b phi(b)) + (1 - Phi(b))``
    (the Gaussian's part between the bounds, plus the mass clipped to 1); over black (``x = 0``,
    only the low side) the variance is ``(1/2 - 1/(2 pi)) s^2 = 0.341 s^2``.

    Args:
        x: clean values, any shape (float).
        sigma: noise std, a number or a tensor broadcastable to `x` (``> 0``).
    """
    s = torch.as_tensor(sigma, dtype=x.dtype, device=x.device).clamp_min(1e-6)
    a, b = _bounds(x, s, low, high)
    m, _ = _mean_and_slope(x, s, low, high)
    cdf_a, cdf_b = torch.special.ndtr(a), torch.special.ndtr(b)
    # t phi(t) -> 0 at t = +-inf (an unclipped side).
    a_phi = torch.where(torch.isfinite(a), a * _phi(a), torch.zeros_like(a))
    b_phi = torch.where(torch.isfinite(b), b * _phi(b), torch.zeros_like(b))
    second = ((x * x + s * s) * (cdf_b - cdf_a) + 2.0 * x * s * (_phi(a) - _phi(b)) + s * s * (a_phi - b_phi)
              + (1.0 - cdf_b))
    return (second - m * m).clamp_min(0.0)


def undo_clipping_bias(mean: Tensor, sigma: float | Tensor, *, low: bool = True, high: bool = True) -> Tensor:
    """The ``x`` in ``[0, 1]`` with ``clipped_mean(x, sigma) = mean``: a clipped photo's estimated mean
    turned into the clean value.

    Args:
        mean: ``E[y]`` estimates (a denoiser's output), any shape, in ``[0, 1]``.
        sigma: the noise std, a number or a tensor broadcastable to `mean`.
        low, high: whether the photo was clipped at 0 / at 1 (`clipped_sides`); a side not clipped
            is not corrected.

    Returns:
        Tensor like `mean`, in ``[0, 1]``. Where `mean` is below ``f(0)`` (or above ``f(1)``) the
        solution lies outside ``[0, 1]`` and is clamped.
    """
    if not (low or high):
        return mean.clamp(0.0, 1.0)
    s = torch.as_tensor(sigma, dtype=mean.dtype, device=mean.device).clamp_min(1e-6)
    x = mean.clone()
    lo, hi = -6.0 * s, 1.0 + 6.0 * s  # f is flat beyond: Newton steps there would overshoot
    for _ in range(NEWTON_ITERS):
        fx, slope = _mean_and_slope(x, s, low, high)
        x = torch.minimum(torch.maximum(x - (fx - mean) / slope.clamp_min(1e-4), lo), hi)
    return x.clamp(0.0, 1.0)


def clipped_sides(noisy: np.ndarray, *, min_fraction: float = MIN_CLIPPED_FRACTION) -> tuple[bool, bool]:
    """Whether a noisy photo (values in ``[0, 1]``) was clipped at 0 and at 1: at least `min_fraction`
    of its values exactly on that side."""
    arr = np.asarray(noisy)
    return bool(np.mean(arr <= 0.0) >= min_fraction), bool(np.mean(arr >= 1.0) >= min_fraction)


def dark_clipped_fraction(noisy: np.ndarray, *, blur_px: float = DARK_CLIPPED_BLUR_PX,
                          min_local: float = DARK_CLIPPED_MIN_LOCAL) -> float:
    """Fraction of a noisy photo's pixels that lie in a dark clipped region (`dark_clipped_mask`).

    Such a region is black (or nearly) under noise clipped at 0: a black background, a shadow. Scattered
    zeros in dark texture (values a few noise std above 0) stay below `min_local`. Measured on the real
    sets at sigma 25/255: the temple ring's photos 0.47-0.72 (their black background), DTU scan24's 0.00-0.11
    (mean 0.03; its clipped values are mostly blown highlights, at 1).

    Args:
        noisy: ``(H, W, C)`` or ``(H, W)`` photo in ``[0, 1]``.
    """
    return float(dark_clipped_mask(noisy, blur_px=blur_px, min_local=min_local).mean())


def dark_clipped_mask(noisy: np.ndarray, *, blur_px: float = DARK_CLIPPED_BLUR_PX,
                      min_local: float = DARK_CLIPPED_MIN_LOCAL) -> np.ndarray:
    """``(H, W)`` bool: the pixels in a dark clipped region, where in some channel at least `min_local` of the
    values in their neighbourhood (Gaussian weights of std `blur_px`) are exactly 0.

    Args:
        noisy: ``(H, W, C)`` or ``(H, W)`` photo in ``[0, 1]``.
    """
    from mvgeo.common.deps import cv2

    arr = np.asarray(noisy, dtype=np.float32)
    zeros = (arr <= 0.0).astype(np.float32)
    local = cv2.GaussianBlur(zeros, (0, 0), blur_px, borderType=cv2.BORDER_REFLECT)
    local = local.reshape(arr.shape)
    dark = local >= min_local
    if dark.ndim == 3:
        dark = dark.any(axis=2)
    return dark
