"""Checks and conversions between the project's numpy images and torch batches.

numpy images are ``(H, W, 3)`` float32 RGB in ``[0, 1]`` (docs/conventions.md);
grayscale ``(H, W)`` / ``(H, W, 1)`` arrays are accepted by the public
functions and returned in the same layout (the network sees three equal
channels and the output channels are averaged).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from mvgeo.common.errors import InputError, ShapeError

MIN_SIDE_PX = 2


def image_to_tensor(img: np.ndarray, *, name: str = "image") -> Tensor:
    """``(H, W)``, ``(H, W, 1)`` or ``(H, W, 3)`` array in ``[0, 1]`` -> ``[3, H, W]`` float32 tensor.

    Raises:
        ShapeError: not an image layout.
        InputError: non-finite values, or a side below `MIN_SIDE_PX`.
    """
    arr = np.asarray(img)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 3):
        raise ShapeError(f"{name}: expected (H, W), (H, W, 1) or (H, W, 3), got {arr.shape}")
    if arr.shape[0] < MIN_SIDE_PX or arr.shape[1] < MIN_SIDE_PX:
        raise InputError(f"{name} is {arr.shape[1]}x{arr.shape[0]} px; at least {MIN_SIDE_PX}x{MIN_SIDE_PX} needed")
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(f"{name} has dtype {arr.dtype}; expected float in [0, 1]",
                         fix="use mvgeo.common.imageio.read_image, which scales 8/16-bit data to [0, 1]")
    if not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or inf values")
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1), dtype=np.float32))


def tensor_to_image(t: Tensor, *, like: np.ndarray) -> np.ndarray:
    """``[3, H, W]`` tensor -> numpy float32 in the layout of `like`, clipped to ``[0, 1]``."""
    out = t.detach().cpu().clamp(0.0, 1.0).numpy().transpose(1, 2, 0)
    like = np.asarray(like)
    if like.ndim == 2:
        out = out.mean(axis=2)
    elif like.shape[2] == 1:
        out = out.mean(axis=2, keepdims=True)
    return np.ascontiguousarray(out, dtype=np.float32)


def images_to_tensors(images: Sequence[np.ndarray]) -> list[Tensor]:
    """Validate and convert a non-empty list of images (errors name the index)."""
    if len(images) == 0:
        raise InputError("no images given", fix="pass at least one image")
    return [image_to_tensor(im, name=f"image {i}") for i, im in enumerate(images)]
