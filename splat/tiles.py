"""Tile binning: which Gaussians touch which 16x16 tile, sorted front to back.

Integer bookkeeping only (no gradients). Memory is O(intersections).

Two implementations of `bin_gaussians` giving identical lists: `"torch"` (the
reference: one integer sort of all intersections keyed by (tile, depth rank)) and
`"cpp"` (`csrc/tiles.cpp`: per-tile counts, prefix sum, and one pass over the
Gaussians in depth order appending to each tile). `"auto"` picks `"cpp"` for CPU
tensors when the kernels build.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from splat import _cpu_kernel
from splat.projection import resolve_backend


@dataclass
class TileBins:
    """Per-tile lists of Gaussians, depth-sorted (front to back).

    Attributes:
        gaussian_ids: (I,) int64 Gaussian index of each tile intersection,
            grouped by tile (row-major tile order), near to far within a tile.
        tile_offsets: (T + 1,) int64; tile `k`'s Gaussians are
            `gaussian_ids[tile_offsets[k]:tile_offsets[k + 1]]`.
        tiles_x, tiles_y: tile grid size; `T = tiles_x * tiles_y`.
        tile_size: tile edge in pixels.
    """

    gaussian_ids: torch.Tensor
    tile_offsets: torch.Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int

    @property
    def max_per_tile(self) -> int:
        if self.tile_offsets.numel() < 2:
            return 0
        return int((self.tile_offsets[1:] - self.tile_offsets[:-1]).max().item())


def bin_gaussians(
    means2d: torch.Tensor,
    extents_px: torch.Tensor,
    depths: torch.Tensor,
    visible: torch.Tensor,
    width: int,
    height: int,
    *,
    tile_size: int = 16,
    backend: str = "torch",
) -> TileBins:
    """Assign each visible Gaussian to every tile its alpha >= 1/255 box overlaps.

    A pixel (row, col) is evaluated at (col + 0.5, row + 0.5); a Gaussian is
    listed in a tile when some pixel centre of the tile lies in its box, so the
    lists are exact supersets of the contributing pairs.

    Args:
        means2d: (N, 2) pixel positions.
        extents_px: (N, 2) box half-widths.
        depths: (N,) sort keys (camera z).
        visible: (N,) bool.
        width, height: image size.
        tile_size: tile edge in pixels.
        backend: "torch" (the reference), "cpp" or "auto" (see the module docstring).

    Returns:
        `TileBins` on the inputs' device.
    """
    device = means2d.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    num_tiles = tiles_x * tiles_y
    if resolve_backend(backend, device) == "cpp":
        dt = means2d.dtype if means2d.dtype in (torch.float32, torch.float64) else torch.float32
        gaussian_ids, tile_offsets = _cpu_kernel.tiles_bin(
            means2d.detach().to(dt).contiguous(), extents_px.detach().to(dt).contiguous(),
            depths.detach().to(dt).contiguous(), visible.to(torch.int32).contiguous(), width, height, tile_size,
            tiles_x, tiles_y)
        return TileBins(gaussian_ids=gaussian_ids, tile_offsets=tile_offsets,
                        tiles_x=tiles_x, tiles_y=tiles_y, tile_size=tile_size)
    ids = torch.nonzero(visible, as_tuple=False).reshape(-1)
    if ids.numel() == 0:
        return TileBins(
            gaussian_ids=torch.zeros(0, dtype=torch.int64, device=device),
            tile_offsets=torch.zeros(num_tiles + 1, dtype=torch.int64, device=device),
            tiles_x=tiles_x, tiles_y=tiles_y, tile_size=tile_size,
        )
    m = means2d.detach()[ids].double()
    e = extents_px.detach()[ids].double()
    # Pixel centres c = col + 0.5 inside [u - e, u + e]  <=>  col in [ceil(u - e - 0.5), floor(u + e - 0.5)].
    # Clamped to the image; an empty range (col1 < col0: no pixel centre in the box) lists no tile.
    col0 = torch.ceil(m[:, 0] - e[:, 0] - 0.5).clamp(min=0)
    col1 = torch.floor(m[:, 0] + e[:, 0] - 0.5).clamp(max=width - 1)
    row0 = torch.ceil(m[:, 1] - e[:, 1] - 0.5).clamp(min=0)
    row1 = torch.floor(m[:, 1] + e[:, 1] - 0.5).clamp(max=height - 1)
    has_pixel = (col1 >= col0) & (row1 >= row0)
    tx0 = torch.div(col0, tile_size, rounding_mode="floor").long()
    tx1 = torch.div(col1, tile_size, rounding_mode="floor").long() + 1
    ty0 = torch.div(row0, tile_size, rounding_mode="floor").long()
    ty1 = torch.div(row1, tile_size, rounding_mode="floor").long() + 1
    nx = torch.where(has_pixel, tx1 - tx0, torch.zeros_like(tx0))
    ny = torch.where(has_pixel, ty1 - ty0, torch.zeros_like(ty0))
    counts = nx * ny
    keep = counts > 0
    ids, tx0, ty0, nx, counts = ids[keep], tx0[keep], ty0[keep], nx[keep], counts[keep]
    # Depth rank (stable) so that one integer sort orders by (tile, depth, id).
    order = torch.argsort(depths.detach()[ids], stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(order.numel(), device=device)

    total = int(counts.sum().item())
    g = torch.repeat_interleave(torch.arange(ids.numel(), device=device), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=device) - start[g]
    nxg = nx[g]
    tile_x = tx0[g] + local % nxg
    tile_y = ty0[g] + torch.div(local, nxg, rounding_mode="floor")
    tile_id = tile_y * tiles_x + tile_x
    key = tile_id * ids.numel() + rank[g]
    sort_idx = torch.sort(key, stable=True).indices
    gaussian_ids = ids[g[sort_idx]]
    tile_counts = torch.bincount(tile_id, minlength=num_tiles)
    tile_offsets = torch.zeros(num_tiles + 1, dtype=torch.int64, device=device)
    tile_offsets[1:] = torch.cumsum(tile_counts, 0)
    return TileBins(gaussian_ids=gaussian_ids, tile_offsets=tile_offsets,
                    tiles_x=tiles_x, tiles_y=tiles_y, tile_size=tile_size)
