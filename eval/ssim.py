"""SSIM as an evaluation metric: the project's one SSIM (`denoise.losses.ssim`) per image.

Wang et al. 2004 with an 11x11 Gaussian window (sigma 1.5), population
covariance, averaged over the pixels whose window lies inside the image: the
numbers of `skimage.metrics.structural_similarity(a, b, gaussian_weights=True,
sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)`.
"""

from __future__ import annotations

import torch

from denoise.losses import ssim as _ssim
from mvgeo.common.errors import ShapeError, check_shape

__all__ = ["SSIM_WINDOW_PX", "ssim"]

SSIM_WINDOW_PX = 11


def ssim(pred: torch.Tensor, target: torch.Tensor, *, data_range: float = 1.0) -> torch.Tensor:
    """Mean SSIM per image (1 for identical images).

    Evaluated in float64 (a metric, not a loss: no float32 cancellation in the
    variance terms `E[x^2] - E[x]^2`).

    Args:
        pred: `[B, C, H, W]`, `H, W >= 11`.
        target: same shape as `pred`.
        data_range: intensity range (1.0 for [0, 1] images).

    Returns:
        `[B]` float64 on `pred`'s device.
    """
    check_shape(pred, ["B", "C", "H", "W"], "pred")
    if tuple(target.shape) != tuple(pred.shape):
        raise ShapeError(f"target: expected shape {tuple(pred.shape)} like pred, got {tuple(target.shape)}")
    if min(pred.shape[-2:]) < SSIM_WINDOW_PX:
        raise ShapeError(f"pred: SSIM needs H, W >= {SSIM_WINDOW_PX} px, got {tuple(pred.shape[-2:])}")
    a = pred.to(torch.float64)
    b = target.to(device=pred.device, dtype=torch.float64)
    return _ssim(a, b, data_range=data_range, window_size=SSIM_WINDOW_PX, sigma=1.5, border="valid",
                 reduction="none")
