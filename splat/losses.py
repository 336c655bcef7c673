"""The photometric loss of 3DGS / InstantSplat: 0.8 L1 + 0.2 (1 - SSIM).

Two paths with one definition: the torch path (`mvgeo.image_metrics.ssim`, autograd; the
reference) and, for CPU float tensors, the fused C++ kernel (`splat/csrc/ssim.cpp`), which
computes the value and the gradient in one call on several threads. The tests compare the two
(values and gradients) and gradient-check the kernel.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch.autograd.function import once_differentiable

from mvgeo.image_filters import gaussian_kernel1d
from mvgeo.image_metrics import SSIM_SIGMA_PX, SSIM_WINDOW_PX, ssim
from mvgeo.image_metrics import psnr as _psnr_db

__all__ = ["LossBackend", "photometric_loss", "psnr"]

LossBackend = Literal["auto", "cpp", "torch"]

#: SSIM's constants for images in [0, 1]: (0.01 L)^2 and (0.03 L)^2 with L = 1 (Wang et al. 2004).
_SSIM_C1 = 0.01**2
_SSIM_C2 = 0.03**2
_TAPS = gaussian_kernel1d(SSIM_WINDOW_PX, SSIM_SIGMA_PX, dtype=torch.float64)


def photometric_loss(rendered: torch.Tensor, target: torch.Tensor, *, ssim_weight: float = 0.2,
                     backend: LossBackend = "auto", num_threads: int | None = None) -> torch.Tensor:
    """`(1 - w) * L1 + w * (1 - SSIM)` with an 11x11, sigma 1.5 Gaussian SSIM window.

    Args:
        rendered, target: [3, H, W] images in [0, 1] (any channel count works).
        ssim_weight: `w` (0.2 in 3DGS).
        backend: "cpp": the fused C++ kernel (CPU float32/float64 only); "torch": the autograd
            reference; "auto": "cpp" when the tensors are on the CPU in float32/float64 and the
            kernels load, else "torch".
        num_threads: threads of the C++ kernel (default `torch.get_num_threads()`); the result
            does not depend on it.

    Returns:
        Scalar loss. SSIM uses reflected borders so every pixel is weighted
        (images smaller than the window fall back to L1 only).

    Raises:
        ValueError: `backend="cpp"` for tensors it cannot take, or an unknown backend.
    """
    if backend not in ("auto", "cpp", "torch"):
        raise ValueError(f"backend must be 'auto', 'cpp' or 'torch', got {backend!r}")
    if ssim_weight == 0.0 or min(rendered.shape[-2:]) < SSIM_WINDOW_PX:
        return (rendered - target).abs().mean()
    if backend != "torch" and _use_cpp(rendered, target, required=backend == "cpp"):
        return _PhotometricLossCpp.apply(rendered, target, float(ssim_weight), num_threads)
    l1 = (rendered - target).abs().mean()
    s = ssim(rendered[None], target[None], border="reflect")
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - s)


def _use_cpp(rendered: torch.Tensor, target: torch.Tensor, *, required: bool) -> bool:
    ok = (rendered.device.type == "cpu" and target.device.type == "cpu" and rendered.dim() == 3
          and rendered.shape == target.shape and rendered.dtype in (torch.float32, torch.float64)
          and target.dtype == rendered.dtype and not target.requires_grad)
    if not ok:
        if required:
            raise ValueError("backend='cpp' needs (C, H, W) CPU float32/float64 tensors of one shape and dtype "
                             "and a target without gradient, got "
                             f"{tuple(rendered.shape)} {rendered.dtype} {rendered.device} and "
                             f"{tuple(target.shape)} {target.dtype} {target.device}")
        return False
    from splat import _cpu_kernel

    if required:
        _cpu_kernel.load()  # raises KernelBuildError with the reason
        return True
    return _cpu_kernel.available()


class _PhotometricLossCpp(torch.autograd.Function):
    """The fused kernel: the value and the gradient by `rendered` in one call (no gradient to `target`)."""

    @staticmethod
    def forward(ctx, rendered, target, ssim_weight, num_threads):
        from splat import _cpu_kernel

        x = rendered.detach().contiguous()
        y = target.detach().contiguous()
        l1, s, grad = _cpu_kernel.photometric_loss(
            x, y, taps=_TAPS, c1=_SSIM_C1, c2=_SSIM_C2, ssim_weight=ssim_weight,
            need_grad=ctx.needs_input_grad[0], num_threads=num_threads)
        ctx.save_for_backward(grad if grad is not None else torch.empty(0))
        value = (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - s)
        return torch.tensor(value, dtype=rendered.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        (grad,) = ctx.saved_tensors
        return grad * grad_out, None, None, None


def psnr(rendered: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB of one [3, H, W] image in [0, 1] (rendered clipped to [0, 1]; `inf` if identical)."""
    return float(_psnr_db(rendered.detach().clamp(0, 1)[None], target.detach()[None])[0])
