"""Random training patches from a list of images (with optional paired targets)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor


def effective_patch_px(images: Sequence[Tensor], patch_px: int) -> int:
    """The patch side actually used: `patch_px`, or the smallest image side if that is smaller."""
    smallest = min(min(t.shape[-2:]) for t in images)
    return int(min(patch_px, smallest))


def sample_patches(images: Sequence[Tensor], *, patch_px: int, batch_size: int, rng: np.random.Generator,
                   paired: Sequence[Tensor] | None = None, augment: bool = True) -> tuple[Tensor, Tensor | None]:
    """Draw `batch_size` square crops, images chosen with probability proportional to their area.

    Args:
        images: ``[C, H, W]`` tensors (sizes may differ), each side >= `patch_px`.
        patch_px: crop side in pixels.
        rng: numpy generator (the only source of randomness).
        paired: optional tensors of the same sizes; the same crop and augmentation
            is applied to them (round 2: the render of the same view).
        augment: random rot90 and horizontal flip (square patches keep their shape).

    Returns:
        ``([B, C, P, P], [B, C', P, P] or None)``.
    """
    areas = np.array([t.shape[-2] * t.shape[-1] for t in images], dtype=np.float64)
    which = rng.choice(len(images), size=batch_size, p=areas / areas.sum())
    crops, pcrops = [], []
    for i in which:
        h, w = images[i].shape[-2:]
        y0 = int(rng.integers(0, h - patch_px + 1))
        x0 = int(rng.integers(0, w - patch_px + 1))
        k = int(rng.integers(0, 4)) if augment else 0
        flip = bool(rng.integers(0, 2)) if augment else False
        for src, dst in ((images, crops), (paired, pcrops)):
            if src is None:
                continue
            c = src[i][:, y0 : y0 + patch_px, x0 : x0 + patch_px]
            if k:
                c = torch.rot90(c, k, dims=(1, 2))
            if flip:
                c = torch.flip(c, dims=(2,))
            dst.append(c)
    return torch.stack(crops), (torch.stack(pcrops) if paired is not None else None)
