"""Gaussian blur of image batches (torch, differentiable), scipy-compatible.

The separable-filter primitives (Gaussian taps, half-sample symmetric padding,
``"valid"``/``"reflect"`` borders) are `mvgeo.image_filters`, shared with the
image metrics.
"""

from __future__ import annotations

from torch import Tensor

from mvgeo.image_filters import Border, gaussian_kernel1d, pad_symmetric, separable_filter

__all__ = ["Border", "gaussian_blur", "gaussian_kernel1d", "pad_symmetric", "separable_filter", "window_size_for_sigma"]


def window_size_for_sigma(sigma: float, *, truncate: float = 4.0) -> int:
    """Taps of scipy's Gaussian for `sigma` and `truncate`: ``2 * int(truncate * sigma + 0.5) + 1``."""
    return 2 * int(truncate * sigma + 0.5) + 1


def gaussian_blur(x: Tensor, *, sigma: float, window_size: int | None = None, border: Border = "reflect") -> Tensor:
    """Gaussian blur of an image batch, per channel (differentiable).

    With the default ``window_size`` (scipy's ``truncate=4``) and
    ``border="reflect"`` this equals ``scipy.ndimage.gaussian_filter(x, sigma,
    mode="reflect")`` over the two spatial axes.

    Args:
        x: ``[B, C, H, W]`` float.
        sigma: standard deviation in pixels.
        window_size: odd tap count; default ``2 * int(4 * sigma + 0.5) + 1``.
        border: see the module docstring.

    Returns:
        ``[B, C, H, W]`` (``reflect``) or the valid part (``valid``), dtype of `x`.
    """
    if window_size is None:
        window_size = window_size_for_sigma(sigma)
    kernel = gaussian_kernel1d(window_size, sigma, dtype=x.dtype, device=x.device)
    return separable_filter(x, kernel, border=border)
