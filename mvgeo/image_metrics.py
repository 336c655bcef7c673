"""Full-reference image metrics (torch): PSNR and SSIM, the one implementation that the
splatting loss (`splat.losses`), the denoiser's round-2 loss (`denoise.round2`) and the
evaluation (`eval.image_metrics`) all use.

Images are batches ``[B, C, H, W]`` (float32 or float64, nominally in ``[0, 1]``) on any
device (docs/conventions.md).

- `ssim` / `ssim_map`: differentiable, in the input's dtype (a loss). With the defaults
  `ssim` equals ``skimage.metrics.structural_similarity(a, b, gaussian_weights=True,
  sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)``.
- `ssim_per_image`, `psnr`: the evaluation metrics, one float64 value per image.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from mvgeo.common.errors import ShapeError, check_shape
from mvgeo.image_filters import Border, gaussian_kernel1d, separable_filter

__all__ = ["SSIM_SIGMA_PX", "SSIM_WINDOW_PX", "Reduction", "psnr", "ssim", "ssim_map", "ssim_per_image"]

Reduction = Literal["mean", "none"]

#: SSIM's Gaussian window (Wang et al. 2004): 11 taps, sigma 1.5 px (scikit-image's truncate=3.5).
SSIM_WINDOW_PX = 11
SSIM_SIGMA_PX = 1.5


def _check_pair(x: Tensor, y: Tensor, names: tuple[str, str] = ("x", "y")) -> None:
    check_shape(x, ["B", "C", "H", "W"], names[0])
    if tuple(x.shape) != tuple(y.shape):
        raise ShapeError(f"{names[1]}: expected shape {tuple(x.shape)} like {names[0]}, got {tuple(y.shape)}")


def ssim_map(x: Tensor, y: Tensor, *, data_range: float = 1.0, window_size: int = SSIM_WINDOW_PX,
             sigma: float = SSIM_SIGMA_PX, border: Border = "valid", k1: float = 0.01, k2: float = 0.03) -> Tensor:
    """Per-pixel SSIM (Wang et al. 2004) with a Gaussian window, per channel.

    Local statistics use population (not sample) covariance, as the paper.

    Args:
        x, y: ``[B, C, H, W]``, same shape, dtype and device.
        data_range: intensity range `L` in ``C1 = (k1 L)^2``, ``C2 = (k2 L)^2``.
        window_size: odd tap count of the Gaussian window (11 for sigma 1.5,
            which is what scikit-image's ``truncate=3.5`` gives).
        sigma: Gaussian standard deviation in pixels.
        border: ``"valid"``: only pixels whose whole window lies inside the
            image, ``[B, C, H - w + 1, W - w + 1]`` (scikit-image's average
            region); ``"reflect"``: every pixel, ``[B, C, H, W]``, statistics
            near the border from a half-sample mirrored image (scipy's
            ``reflect``, the map scikit-image returns with ``full=True``).

    Returns:
        The map in `x`'s dtype (shape above).

    Raises:
        ShapeError: shapes differ or the image is smaller than the window
            with ``border="valid"``.
    """
    _check_pair(x, y)
    c = x.shape[1]
    kernel = gaussian_kernel1d(window_size, sigma, dtype=x.dtype, device=x.device)
    # One filtering pass over the five moment images.
    stats = separable_filter(torch.cat([x, y, x * x, y * y, x * y], dim=1), kernel, border=border)
    mx, my, mxx, myy, mxy = stats.split(c, dim=1)
    vx = mxx - mx * mx
    vy = myy - my * my
    cxy = mxy - mx * my
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    num = (2 * mx * my + c1) * (2 * cxy + c2)
    den = (mx * mx + my * my + c1) * (vx + vy + c2)
    return num / den


def ssim(x: Tensor, y: Tensor, *, data_range: float = 1.0, window_size: int = SSIM_WINDOW_PX,
         sigma: float = SSIM_SIGMA_PX, border: Border = "valid", reduction: Reduction = "mean") -> Tensor:
    """Mean SSIM of two image batches (differentiable; 1 for identical images).

    The mean runs over channels and the pixels kept by `border` (see
    `ssim_map`); ``"valid"`` (default) reproduces scikit-image, which averages
    only away from the border. Use ``border="reflect"`` to weigh every pixel
    (e.g. a training loss on small crops).

    Args:
        x, y: ``[B, C, H, W]``, same shape, dtype and device.
        data_range: ``max - min`` of the intensity scale (1.0 for ``[0, 1]``).
        window_size: odd Gaussian window size in pixels.
        sigma: Gaussian standard deviation in pixels.
        border: ``"valid"`` or ``"reflect"``.
        reduction: ``"mean"``: scalar over the batch; ``"none"``: ``[B]``.

    Returns:
        Scalar (or ``[B]``) tensor of `x`'s dtype.
    """
    per_pixel = ssim_map(x, y, data_range=data_range, window_size=window_size, sigma=sigma, border=border)
    if reduction == "mean":
        return per_pixel.mean()
    if reduction == "none":
        return per_pixel.flatten(1).mean(1)
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


def ssim_per_image(pred: Tensor, target: Tensor, *, data_range: float = 1.0) -> Tensor:
    """Mean SSIM per image, the evaluation metric (1 for identical images).

    `ssim` with the 11x11, sigma 1.5 window and the ``"valid"`` border (scikit-image's
    numbers), evaluated in float64: a metric, not a loss, so no float32 cancellation in
    the variance terms ``E[x^2] - E[x]^2``.

    Args:
        pred: ``[B, C, H, W]``, ``H, W >= 11``.
        target: same shape as `pred`.
        data_range: intensity range (1.0 for ``[0, 1]`` images).

    Returns:
        ``[B]`` float64 on `pred`'s device.

    Raises:
        ShapeError: shapes differ, or an image side is below 11 px.
    """
    _check_pair(pred, target, ("pred", "target"))
    if min(pred.shape[-2:]) < SSIM_WINDOW_PX:
        raise ShapeError(f"pred: SSIM needs H, W >= {SSIM_WINDOW_PX} px, got {tuple(pred.shape[-2:])}")
    a = pred.to(torch.float64)
    b = target.to(device=pred.device, dtype=torch.float64)
    return ssim(a, b, data_range=data_range, border="valid", reduction="none")


def psnr(pred: Tensor, target: Tensor, *, data_range: float = 1.0) -> Tensor:
    """PSNR in dB per image, ``10 log10(data_range^2 / MSE)``, MSE over all channels and pixels.

    Computed in float64 so that values above ~50 dB are not limited by float32
    rounding of the squared error.

    Args:
        pred: ``[B, C, H, W]`` images.
        target: same shape as `pred`.
        data_range: peak-to-peak intensity range (1.0 for ``[0, 1]`` images).

    Returns:
        ``[B]`` float64 on `pred`'s device; ``inf`` where the images are identical.

    Raises:
        ShapeError: shapes differ.
        ValueError: `data_range` is not positive.
    """
    _check_pair(pred, target, ("pred", "target"))
    if not data_range > 0:
        raise ValueError(f"data_range must be positive, got {data_range}")
    diff = pred.to(torch.float64) - target.to(device=pred.device, dtype=torch.float64)
    mse = (diff * diff).mean(dim=(1, 2, 3))
    return 10.0 * torch.log10(data_range**2 / mse)
