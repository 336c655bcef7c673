"""Peak signal-to-noise ratio."""

from __future__ import annotations

import torch

from mvgeo.common.errors import ShapeError, check_shape

__all__ = ["psnr"]


def psnr(pred: torch.Tensor, target: torch.Tensor, *, data_range: float = 1.0) -> torch.Tensor:
    """PSNR in dB per image, `10 log10(data_range^2 / MSE)`, MSE over all channels and pixels.

    Computed in float64 so that values above ~50 dB are not limited by float32
    rounding of the squared error.

    Args:
        pred: `[B, C, H, W]` images.
        target: same shape as `pred`.
        data_range: peak-to-peak intensity range (1.0 for [0, 1] images).

    Returns:
        `[B]` float64 on `pred`'s device; `inf` where the images are identical.
    """
    check_shape(pred, ["B", "C", "H", "W"], "pred")
    if tuple(target.shape) != tuple(pred.shape):
        raise ShapeError(f"target: expected shape {tuple(pred.shape)} like pred, got {tuple(target.shape)}")
    if not data_range > 0:
        raise ValueError(f"data_range must be positive, got {data_range}")
    diff = pred.to(torch.float64) - target.to(device=pred.device, dtype=torch.float64)
    mse = (diff * diff).mean(dim=(1, 2, 3))
    return 10.0 * torch.log10(data_range**2 / mse)
