"""Neighbor2Neighbor (Huang et al. 2021): training pairs from one noisy image by neighbour sub-sampling.

The image is cut into 2x2 cells. In each cell, one ordered pair of *edge-adjacent*
pixels is drawn uniformly from the 8 such pairs (4 adjacent pairs, 2 orders); the
first pixel goes to sub-image ``g1(y)``, the second to ``g2(y)`` (each
``H/2 x W/2``). With pixel-independent noise the two sub-images are noisy
observations of nearly the same signal with independent noise, so a network
trained to map ``g1(y)`` to ``g2(y)`` learns a denoiser (Noise2Noise). The paper's
regulariser corrects for the small signal difference between the neighbours:

``L = |f(g1(y)) - g2(y)|^2 + gamma |f(g1(y)) - g2(y) - (g1(f(y)) - g2(f(y)))|^2``

with ``f(y)`` computed without gradient, sub-sampled with the *same* pixel choice
(`neighbor2neighbor_loss` in `denoise.losses`). At inference the network runs on
the full noisy image.
"""

from __future__ import annotations

import torch
from torch import Tensor

from mvgeo.common.errors import ShapeError, check_shape

#: The 8 ordered pairs of edge-adjacent positions in a 2x2 cell, positions numbered
#: ``2 * dy + dx`` (0: top-left, 1: top-right, 2: bottom-left, 3: bottom-right).
NEIGHBOUR_PAIRS: tuple[tuple[int, int], ...] = (
    (0, 1), (1, 0), (2, 3), (3, 2),  # horizontal neighbours
    (0, 2), (2, 0), (1, 3), (3, 1),  # vertical neighbours
)


def neighbour_choice(batch: int, h: int, w: int, *, generator: torch.Generator | None = None,
                     device: torch.device | str = "cpu") -> Tensor:
    """A random pair index in ``0..7`` (into `NEIGHBOUR_PAIRS`) per 2x2 cell.

    Args:
        batch, h, w: batch size and image size in pixels (``h, w >= 2``).

    Returns:
        ``[B, h // 2, w // 2]`` int64.
    """
    if h < 2 or w < 2:
        raise ShapeError(f"neighbour sub-sampling needs images of at least 2x2 px, got {h}x{w}")
    return torch.randint(0, len(NEIGHBOUR_PAIRS), (batch, h // 2, w // 2), generator=generator, device=device)


def neighbour_subsample(x: Tensor, choice: Tensor) -> tuple[Tensor, Tensor]:
    """The two sub-images ``g1(x), g2(x)`` for a given per-cell pair choice.

    An odd last row/column is dropped (it belongs to no full cell).

    Args:
        x: ``[B, C, H, W]``.
        choice: ``[B, H // 2, W // 2]`` indices into `NEIGHBOUR_PAIRS` (`neighbour_choice`).

    Returns:
        ``(g1, g2)``, each ``[B, C, H // 2, W // 2]``.
    """
    check_shape(x, ["B", "C", "H", "W"], "x")
    b, c, h, w = x.shape
    hh, wh = h // 2, w // 2
    check_shape(choice, [b, hh, wh], "choice")
    cells = x[..., : 2 * hh, : 2 * wh].reshape(b, c, hh, 2, wh, 2).permute(0, 1, 2, 4, 3, 5).reshape(b, c, hh, wh, 4)
    pairs = torch.tensor(NEIGHBOUR_PAIRS, device=x.device)  # (8, 2)
    first = pairs[choice, 0][:, None, :, :, None].expand(b, c, hh, wh, 1)
    second = pairs[choice, 1][:, None, :, :, None].expand(b, c, hh, wh, 1)
    return cells.gather(4, first)[..., 0], cells.gather(4, second)[..., 0]
