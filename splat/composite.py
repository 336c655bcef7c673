"""Front-to-back alpha compositing of depth-sorted 2D Gaussians per tile.

Two implementations of one function, `composite_tiles`:

- `"torch"`: `_composite_tiles_torch`, plain torch on any device, autograd
  for the backward. Tiles are processed in chunks, each a dense
  (tiles, pixels-per-tile, Gaussians-per-tile) block, under activation
  checkpointing, so memory is bounded by pixels x Gaussians-per-tile (one
  chunk at a time), never pixels x all Gaussians. This is the reference the
  C++ kernel is tested against.
- `"cpp"`: the C++ kernel (`csrc/composite.cpp`) with a hand-written
  backward, CPU only, float32/float64.

`"auto"` picks `"cpp"` for CPU tensors when the kernel builds, else `"torch"`
(one warning per process says why the kernel is unavailable).
Rules (3DGS / gsplat): alpha = min(ALPHA_MAX, o exp(-sigma)); contributions with
alpha < ALPHA_MIN (or sigma < 0) are skipped; a pixel stops before the Gaussian
that would take its transmittance to <= TRANSMITTANCE_MIN. Both paths use these
constants: the C++ kernel receives them as arguments.
"""

from __future__ import annotations

from typing import Literal

import torch

from splat import _cpu_kernel
from splat.projection import ALPHA_MIN
from splat.tiles import TileBins

#: Upper bound of one Gaussian's alpha (3DGS), so that no layer is fully opaque.
ALPHA_MAX = 0.99
#: A pixel stops before the Gaussian that would bring its transmittance to or below this.
TRANSMITTANCE_MIN = 1e-4

Backend = Literal["auto", "torch", "cpp"]

#: Elements (pixels x Gaussians) per chunk of the torch path; ~25 tensors of this size live at once.
_TORCH_CHUNK_ELEMS = 2_000_000


def composite_tiles(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    bins: TileBins,
    width: int,
    height: int,
    *,
    backend: Backend = "auto",
    num_threads: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite features of all Gaussians into an image.

    Args:
        means2d: (N, 2) pixel positions.
        conics: (N, 3) inverse 2D covariance (a, b, c).
        colors: (N, C) features to composite (RGB, depth, ...).
        opacities: (N,) in [0, 1].
        bins: depth-sorted tile lists from `bin_gaussians`.
        width, height: image size.
        backend: "auto", "torch" or "cpp".
        num_threads: threads of the C++ kernel (default `torch.get_num_threads()`); the result
            does not depend on it. Ignored by the torch path.

    Returns:
        accum: (H, W, C) `sum_i f_i alpha_i T_i` (no background).
        transmittance: (H, W) final transmittance `T` (alpha = 1 - T).
    """
    if backend == "auto":
        backend = "cpp" if (means2d.device.type == "cpu" and _cpu_kernel.available()) else "torch"
    if backend == "cpp":
        if means2d.device.type != "cpu":
            raise ValueError("the cpp compositor runs on CPU tensors only; use backend='torch' on CUDA")
        return _CompositeCpp.apply(means2d, conics, colors, opacities, bins, width, height, num_threads)
    if backend == "torch":
        return _composite_tiles_torch(means2d, conics, colors, opacities, bins, width, height)
    raise ValueError(f"unknown compositing backend {backend!r} (use 'auto', 'torch' or 'cpp')")


class _CompositeCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, bins, width, height, num_threads):
        dt = colors.dtype
        tensors = [t.detach().to(dt).contiguous() for t in (means2d, conics, colors, opacities)]
        accum, trans, last = _cpu_kernel.forward(bins, *tensors, width, height, alpha_min=ALPHA_MIN,
                                                 alpha_max=ALPHA_MAX, transmittance_min=TRANSMITTANCE_MIN,
                                                 num_threads=num_threads)
        ctx.bins, ctx.width, ctx.height, ctx.num_threads = bins, width, height, num_threads
        ctx.save_for_backward(*tensors, trans, last)
        ctx.mark_non_differentiable(last)
        return accum, trans

    @staticmethod
    def backward(ctx, grad_accum, grad_trans):
        m, c, col, o, trans, last = ctx.saved_tensors
        bins = ctx.bins
        dt = col.dtype
        grad_accum = torch.zeros_like(trans[..., None].expand(*trans.shape, col.shape[1])) if grad_accum is None \
            else grad_accum.to(dt).contiguous()
        grad_trans = torch.zeros_like(trans) if grad_trans is None else grad_trans.to(dt).contiguous()
        rows = _cpu_kernel.backward(bins, m, c, col, o, ctx.width, ctx.height, trans, last, grad_accum, grad_trans,
                                    alpha_min=ALPHA_MIN, alpha_max=ALPHA_MAX, num_threads=ctx.num_threads)
        # One deterministic sum of the per-intersection rows per Gaussian (`_cpu_kernel.gather`).
        out_m, out_c, out_o, out_col = _cpu_kernel.gather(bins.gaussian_ids, rows, m.shape[0],
                                                          num_threads=ctx.num_threads)
        return out_m, out_c, out_col, out_o, None, None, None, None


class _RecomputedChunk(torch.autograd.Function):
    """Activation checkpointing of one chunk: forward without a graph, rebuilt in backward.

    (torch.utils.checkpoint does the same but pulls in torch._dynamo on first use, seconds of import.)
    """

    @staticmethod
    def forward(ctx, pix, idx, pad, means2d, conics, colors, opacities):
        ctx.save_for_backward(pix, idx, pad, means2d, conics, colors, opacities)
        with torch.no_grad():
            return _composite_chunk(pix, idx, pad, means2d, conics, colors, opacities)

    @staticmethod
    def backward(ctx, grad_acc, grad_tr):
        pix, idx, pad, *inputs = ctx.saved_tensors
        inputs = [t.detach().requires_grad_(t.requires_grad) for t in inputs]
        with torch.enable_grad():
            acc, tr = _composite_chunk(pix, idx, pad, *inputs)
            wanted = [t for t in inputs if t.requires_grad]
            grads = iter(torch.autograd.grad((acc, tr), wanted, (grad_acc, grad_tr), allow_unused=True))
        out = [next(grads) if t.requires_grad else None for t in inputs]
        out = [torch.zeros_like(t) if (g is None and t.requires_grad) else g for t, g in zip(inputs, out, strict=True)]
        return (None, None, None, *out)


def _composite_chunk(pix, idx, pad, means2d, conics, colors, opacities):
    """Dense block: pix (T, P, 2), idx/pad (T, K). Returns accum (T, P, C), trans (T, P)."""
    m = means2d[idx]  # (T, K, 2)
    con = conics[idx]  # (T, K, 3)
    o = opacities[idx]  # (T, K)
    f = colors[idx]  # (T, K, C)
    dx = m[:, None, :, 0] - pix[:, :, None, 0]  # (T, P, K)
    dy = m[:, None, :, 1] - pix[:, :, None, 1]
    sigma = 0.5 * (con[:, None, :, 0] * dx * dx + con[:, None, :, 2] * dy * dy) + con[:, None, :, 1] * dx * dy
    alpha = torch.clamp(o[:, None, :] * torch.exp(-sigma.clamp(min=0)), max=ALPHA_MAX)
    valid = pad[:, None, :] & (sigma >= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    next_t = torch.cumprod(one_minus, dim=-1)
    included = valid & (next_t > TRANSMITTANCE_MIN)
    t_before = torch.cat([torch.ones_like(next_t[..., :1]), next_t[..., :-1]], dim=-1)
    w = torch.where(included, alpha * t_before, torch.zeros_like(alpha))
    accum = torch.einsum("tpk,tkc->tpc", w, f)
    trans = torch.where(included, one_minus, torch.ones_like(one_minus)).prod(dim=-1)
    return accum, trans


def _composite_tiles_torch(means2d, conics, colors, opacities, bins: TileBins, width: int, height: int):
    device, dtype = colors.device, colors.dtype
    ts = bins.tile_size
    num_tiles = bins.tiles_x * bins.tiles_y
    C = colors.shape[1]
    counts = bins.tile_offsets[1:] - bins.tile_offsets[:-1]
    local = torch.arange(ts, device=device, dtype=dtype) + 0.5
    yy, xx = torch.meshgrid(local, local, indexing="ij")
    local_pix = torch.stack([xx.reshape(-1), yy.reshape(-1)], -1)  # (P, 2)
    tile_ids = torch.arange(num_tiles, device=device)
    tile_row = torch.div(tile_ids, bins.tiles_x, rounding_mode="floor")
    origin = torch.stack([(tile_ids % bins.tiles_x) * ts, tile_row * ts], -1).to(dtype)
    need_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (means2d, conics, colors, opacities))
    acc_parts, trans_parts = [], []
    counts_list = counts.tolist()
    start = 0
    while start < num_tiles:
        # Grow the chunk while the dense block stays under the element budget.
        end, kmax = start, 0
        while end < num_tiles:
            k_new = max(kmax, counts_list[end])
            if end > start and (end + 1 - start) * ts * ts * max(k_new, 1) > _TORCH_CHUNK_ELEMS:
                break
            kmax, end = k_new, end + 1
        nt = end - start
        if kmax == 0:
            acc_parts.append(torch.zeros(nt, ts * ts, C, device=device, dtype=dtype))
            trans_parts.append(torch.ones(nt, ts * ts, device=device, dtype=dtype))
            start = end
            continue
        offs = bins.tile_offsets[start:end]
        k = torch.arange(kmax, device=device)
        pad = k[None, :] < counts[start:end, None]
        flat = torch.clamp(offs[:, None] + k[None, :], max=max(bins.gaussian_ids.numel() - 1, 0))
        idx = torch.where(pad, bins.gaussian_ids[flat], torch.zeros_like(flat))
        pix = origin[start:end, None, :] + local_pix[None]
        if need_grad:
            acc, tr = _RecomputedChunk.apply(pix, idx, pad, means2d, conics, colors, opacities)
        else:
            acc, tr = _composite_chunk(pix, idx, pad, means2d, conics, colors, opacities)
        acc_parts.append(acc)
        trans_parts.append(tr)
        start = end
    if need_grad and not any(t.requires_grad for t in acc_parts):
        # Nothing touched any tile: keep the outputs in the graph (all gradients are zero), as the cpp path does.
        tie = sum((t * 0).sum() for t in (means2d, conics, colors, opacities) if t.requires_grad)
        acc_parts = [t + tie for t in acc_parts]
        trans_parts = [t + tie for t in trans_parts]
    acc = torch.cat(acc_parts, 0).reshape(bins.tiles_y, bins.tiles_x, ts, ts, C)
    tr = torch.cat(trans_parts, 0).reshape(bins.tiles_y, bins.tiles_x, ts, ts)
    acc = acc.permute(0, 2, 1, 3, 4).reshape(bins.tiles_y * ts, bins.tiles_x * ts, C)[:height, :width]
    tr = tr.permute(0, 2, 1, 3).reshape(bins.tiles_y * ts, bins.tiles_x * ts)[:height, :width]
    return acc, tr
