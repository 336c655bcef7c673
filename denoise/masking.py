"""Noise2Void blind-spot masking: choose pixels, replace their values.

Each pixel is masked independently with probability `p` (the same pixels in
every channel). Replacement strategies:

- ``"permute"`` (N2V paper, the default): the value at a randomly permuted
  pixel position of the same batch element (a training patch, or the whole
  image at inference);
- ``"uniform_withCP"`` (N2V's local manipulator): the value at a uniformly
  random position of the ``(2 r + 1)^2`` window around the pixel, the centre
  pixel included;
- ``"median"`` (N2V2): the per-channel median of the window without the centre
  pixel (the lower median of its values), the window cropped at the image's edge
  as N2V2's reference does.

For ``"uniform_withCP"`` window positions outside the image are mirrored back
(half-sample symmetric).
All randomness comes from the `generator` argument.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from mvgeo.common.errors import check_shape

Replacement = Literal["permute", "uniform_withCP", "median"]
REPLACEMENTS: tuple[str, ...] = ("permute", "uniform_withCP", "median")


@dataclass(frozen=True)
class MaskedBatch:
    """A masked batch and where it was masked.

    Attributes:
        masked: ``[B, C, H, W]`` input with replaced values at masked pixels.
        mask: ``[B, 1, H, W]`` bool, True where a pixel was replaced.
    """

    masked: Tensor
    mask: Tensor


def reflect_index(idx: Tensor, n: int) -> Tensor:
    """Map integer positions onto ``0..n-1`` by half-sample symmetric mirroring (any distance)."""
    period = 2 * n
    idx = torch.remainder(idx, period)
    return torch.where(idx >= n, period - 1 - idx, idx)


def mask_pixels(x: Tensor, *, p: float = 0.04, replacement: Replacement = "permute", radius: int = 5,
                generator: torch.Generator | None = None) -> MaskedBatch:
    """Blind-spot masking of an image batch.

    Args:
        x: ``[B, C, H, W]``.
        p: probability that a pixel is masked, in ``[0, 1]``.
        replacement: see the module docstring.
        radius: window radius `r` for ``uniform_withCP`` and ``median``.
        generator: torch generator on `x`'s device (seeded by the caller).

    Returns:
        `MaskedBatch` with the masked copy and the mask.
    """
    check_shape(x, ["B", "C", "H", "W"], "x")
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"p must be in [0, 1], got {p}")
    if radius < 1:
        raise ValueError(f"radius must be >= 1, got {radius}")
    b, c, h, w = x.shape
    dev = x.device
    mask = torch.rand((b, 1, h, w), generator=generator, device=dev) < p
    flat = x.reshape(b, c, h * w)
    if replacement == "permute":
        src = torch.argsort(torch.rand((b, h * w), generator=generator, device=dev), dim=1)
        repl = flat.gather(2, src[:, None, :].expand(b, c, h * w)).reshape(b, c, h, w)
        masked = torch.where(mask, repl, x)
    elif replacement == "uniform_withCP":
        dy = torch.randint(-radius, radius + 1, (b, h, w), generator=generator, device=dev)
        dx = torch.randint(-radius, radius + 1, (b, h, w), generator=generator, device=dev)
        rows = reflect_index(torch.arange(h, device=dev)[None, :, None] + dy, h)
        cols = reflect_index(torch.arange(w, device=dev)[None, None, :] + dx, w)
        src = (rows * w + cols).reshape(b, 1, h * w).expand(b, c, h * w)
        masked = torch.where(mask, flat.gather(2, src).reshape(b, c, h, w), x)
    elif replacement == "median":
        masked = x.clone()
        bi, _, yi, xi = torch.nonzero(mask, as_tuple=True)
        if bi.numel():
            off = torch.arange(-radius, radius + 1, device=dev)
            oy, ox = torch.meshgrid(off, off, indexing="ij")
            keep = (oy != 0) | (ox != 0)
            oy, ox = oy[keep], ox[keep]  # (K,) window offsets without the centre
            rows, cols = yi[:, None] + oy[None, :], xi[:, None] + ox[None, :]
            # The window is cropped at the image's edge: mirrored back, its positions would land on the centre
            # pixel itself near the edge (in the outer `radius` rows and columns) and leak its noise.
            inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
            vals = x[bi[:, None], :, rows.clamp(0, h - 1), cols.clamp(0, w - 1)]  # (M, K, C)
            vals = vals.masked_fill(~inside[:, :, None], float("nan"))
            masked[bi, :, yi, xi] = vals.nanmedian(dim=1).values
    else:
        raise ValueError(f"replacement must be one of {REPLACEMENTS}, got {replacement!r}")
    return MaskedBatch(masked=masked, mask=mask)
