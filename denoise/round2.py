"""Round 2: fine-tune the N2V UNet so its outputs agree with the round-1 renders.

For view i the network gets the noisy photo ``noisy_i`` (optionally N2V-masked,
so that K-pass inference stays valid) and produces ``out_i``. The joint loss
(`joint_loss`, weights in `Round2Config`) has

- a **low-frequency** term, ``Charbonnier(blur(out_i), blur(noisy_i))``: the
  view keeps its own colours and shading (noise is zero-mean and is blurred
  away; the render may be slightly off in exposure or geometry);
- **detail** terms against the round-1 render ``render_i`` (multi-view
  consistent, noise-free): Charbonnier of the high-pass parts
  ``out - blur(out)`` vs ``render - blur(render)``, ``1 - SSIM(out, render)``,
  gradient consistency, and chroma consistency (Cb, Cr of YCbCr);
- optional total variation of ``out``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from denoise.filters import gaussian_blur
from denoise.images import images_to_tensors
from denoise.losses import charbonnier, chroma_loss, gradient_loss, ssim, total_variation
from denoise.masking import mask_pixels
from denoise.model import N2VModel
from denoise.n2v import lr_factor
from denoise.patches import effective_patch_px, sample_patches
from mvgeo.common.errors import ConfigError, InputError
from mvgeo.common.progress import progress_bar


@dataclass(frozen=True)
class Round2Config:
    """Round-2 fine-tuning options and loss weights (defaults documented per field).

    Attributes:
        w_low: low-frequency Charbonnier(blur(out), blur(noisy)) (1.0: the anchor to the photo).
        w_detail: Charbonnier between high-pass parts of out and render (1.0).
        w_ssim: ``1 - SSIM(out, render)`` (0.2, the 3DGS L1/SSIM balance).
        w_grad: gradient consistency with the render (0.5).
        w_chroma: chroma (CbCr) consistency with the render (0.5; renders have no chroma noise).
        w_tv: total variation of out (0: off; the render already supplies the smoothness).
        blur_sigma: Gaussian sigma (px) separating low and high frequencies (2.0).
        charbonnier_eps: Charbonnier epsilon in [0, 1] units (1e-3).
        steps, batch_size, patch_px, lr: fine-tuning schedule (Adam, cosine decay, no warm-up).
        mask_input: apply the model's N2V masking to the input (keeps the network usable with
            K-pass inference).
    """

    w_low: float = 1.0
    w_detail: float = 1.0
    w_ssim: float = 0.2
    w_grad: float = 0.5
    w_chroma: float = 0.5
    w_tv: float = 0.0
    blur_sigma: float = 2.0
    charbonnier_eps: float = 1e-3
    steps: int = 200
    batch_size: int = 8
    patch_px: int = 64
    lr: float = 2e-4
    mask_input: bool = True

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name.startswith("w_") and not v >= 0:
                raise ConfigError(f"loss weight must be >= 0, got {v}", key=f.name)
        for key in ("steps", "batch_size", "patch_px"):
            if getattr(self, key) < 1:
                raise ConfigError(f"must be >= 1, got {getattr(self, key)}", key=key)
        if not (self.lr > 0 and self.blur_sigma > 0 and self.charbonnier_eps > 0):
            raise ConfigError("lr, blur_sigma and charbonnier_eps must be > 0", key="lr")


@dataclass(frozen=True)
class Round2Terms:
    """The weighted total and the unweighted terms of `joint_loss` (scalars)."""

    total: Tensor
    low: Tensor
    detail: Tensor
    ssim: Tensor
    grad: Tensor
    chroma: Tensor
    tv: Tensor


def joint_loss(out: Tensor, noisy: Tensor, render: Tensor, config: Round2Config | None = None) -> Round2Terms:
    """The round-2 loss of a batch.

    Args:
        out: ``[B, 3, H, W]`` network output, ``[0, 1]`` units.
        noisy: ``[B, 3, H, W]`` the (unmasked) noisy input.
        render: ``[B, 3, H, W]`` the round-1 render of the same view.
        config: weights (default `Round2Config()`).

    Returns:
        `Round2Terms`. SSIM uses the ``reflect`` border so that small patches count every pixel.
    """
    cfg = config or Round2Config()
    eps, s = cfg.charbonnier_eps, cfg.blur_sigma
    blur_out = gaussian_blur(out, sigma=s)
    low = charbonnier(blur_out, gaussian_blur(noisy, sigma=s), eps=eps)
    detail = charbonnier(out - blur_out, render - gaussian_blur(render, sigma=s), eps=eps)
    ssim_term = 1.0 - ssim(out, render, border="reflect")
    grad = gradient_loss(out, render)
    chroma = chroma_loss(out, render, eps=eps)
    tv = total_variation(out)
    total = (cfg.w_low * low + cfg.w_detail * detail + cfg.w_ssim * ssim_term + cfg.w_grad * grad
             + cfg.w_chroma * chroma + cfg.w_tv * tv)
    return Round2Terms(total=total, low=low, detail=detail, ssim=ssim_term, grad=grad, chroma=chroma, tv=tv)


def finetune_round2(model: N2VModel, noisy_images: Sequence[np.ndarray], renders: Sequence[np.ndarray],
                    config: Round2Config | None = None, *, seed: int = 0) -> N2VModel:
    """Fine-tune `model` in place with the joint loss and return it.

    Args:
        model: the round-1 model (its normalisation is kept).
        noisy_images: ``(H, W, 3)`` float32 [0, 1], the selected noisy views.
        renders: the round-1 renders of the same views, same sizes.
        config: loss weights and schedule.
        seed: seeds patches and masks.

    Raises:
        InputError: counts or sizes differ, or an image is unusable.
    """
    cfg = config or Round2Config()
    if len(noisy_images) != len(renders):
        raise InputError(f"{len(noisy_images)} noisy images but {len(renders)} renders",
                         fix="pass one render per noisy view, in the same order")
    noisy_t = images_to_tensors(noisy_images)
    render_t = images_to_tensors(renders)
    for i, (a, b) in enumerate(zip(noisy_t, render_t, strict=True)):
        if a.shape != b.shape:
            raise InputError(f"view {i}: noisy image is {tuple(a.shape[1:])} but render is {tuple(b.shape[1:])}",
                             fix="render at the photo's resolution")
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed)
    patch = effective_patch_px(noisy_t, cfg.patch_px)
    unet = model.unet
    unet.train()
    opt = torch.optim.Adam(unet.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: lr_factor(s, steps=cfg.steps, warmup_frac=0.0, min_lr_frac=0.05))
    with progress_bar(desc="round2", total=cfg.steps) as bar:
        for _ in range(cfg.steps):
            noisy, render = sample_patches(noisy_t, patch_px=patch, batch_size=cfg.batch_size, rng=rng,
                                           paired=render_t)
            inp = noisy
            if cfg.mask_input:
                inp = mask_pixels(noisy, p=model.mask_prob, replacement=model.replacement, radius=model.radius,
                                  generator=gen).masked
            terms = joint_loss(model.apply(inp), noisy, render, cfg)
            opt.zero_grad(set_to_none=True)
            terms.total.backward()
            opt.step()
            sched.step()
            model.history.append(terms.total.item())
            bar.update(1)
    unet.eval()
    model.blind_spot = False  # trained on the full input now: no centre-pixel fusion at inference
    return model
