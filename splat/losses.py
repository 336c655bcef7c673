"""The photometric loss of 3DGS / InstantSplat: 0.8 L1 + 0.2 (1 - SSIM)."""

from __future__ import annotations

import torch

from mvgeo.image_metrics import psnr as _psnr_db
from mvgeo.image_metrics import ssim


def photometric_loss(rendered: torch.Tensor, target: torch.Tensor, *, ssim_weight: float = 0.2) -> torch.Tensor:
    """`(1 - w) * L1 + w * (1 - SSIM)` with an 11x11, sigma 1.5 Gaussian SSIM window.

    Args:
        rendered, target: [3, H, W] images in [0, 1].
        ssim_weight: `w` (0.2 in 3DGS).

    Returns:
        Scalar loss. SSIM uses reflected borders so every pixel is weighted
        (images smaller than the window fall back to L1 only).
    """
    l1 = (rendered - target).abs().mean()
    if ssim_weight == 0.0 or min(rendered.shape[-2:]) < 11:
        return l1
    s = ssim(rendered[None], target[None], border="reflect")
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - s)


def psnr(rendered: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of one [3, H, W] image in [0, 1] (rendered clipped to [0, 1]; `inf` if identical)."""
    return float(_psnr_db(rendered.detach().clamp(0, 1)[None], target.detach()[None])[0])
