"""The objective of DUSt3R's global alignment (`mvgeo.align.global_align`) and its gradients.

`alignment_loss` is the objective in torch (autograd; any device); `alignment_loss_and_grads` the same value
and gradient by the chain rule in numpy float64 (the CPU path: one long axis per elementwise op instead of
~250 small torch ops); `alignment_loss_reference` the slow loops the tests compare both against. `Adam` is
the optimiser the alignment steps with.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from mvgeo.align.pairs import PairPrediction
from mvgeo.align.pointmap_geometry import pixel_rays
from mvgeo.common.errors import InputError
from mvgeo.transforms_torch import R_from_quat

__all__ = ["Adam", "alignment_loss", "alignment_loss_and_grads", "alignment_loss_reference", "world_points"]



@dataclass
class _Terms:
    """All (edge, view, pixel) residual terms, flattened and sorted by edge (torch tensors).

    Terms of pair e occupy `edge_start[e]:edge_start[e + 1]`.
    """

    flat: torch.Tensor  # (M,) long, index into the concatenated pixels of all views
    pred: torch.Tensor  # (M, 3) pair-frame points
    weight: torch.Tensor  # (M,) log(conf) / (H_v W_v)
    edge_start: list[int]


def _sample_mask(H: int, W: int, stride: int) -> np.ndarray:
    """(H * W,) bool: the pixels on every `stride`-th row and column (offset stride // 2)."""
    m = np.zeros((H, W), bool)
    m[stride // 2::stride, stride // 2::stride] = True
    return m.reshape(-1)


def _build_terms(preds: Sequence[PairPrediction], sizes_hw: Sequence[tuple[int, int]], offsets: np.ndarray,
                 dtype: torch.dtype, device: torch.device, stride: int = 1) -> _Terms:
    flats, pts, wts, starts = [], [], [], [0]
    for p in preds:
        count = 0
        for v, P, C in ((p.i, p.pts_i, p.conf_i), (p.j, p.pts_j, p.conf_j)):
            H, W = sizes_hw[v]
            if P.shape[:2] != (H, W):
                raise InputError(f"pair ({p.i}, {p.j}): pointmap of view {v} is {P.shape[:2]}, expected {(H, W)}")
            c = np.asarray(C, np.float64).reshape(-1)
            P = np.asarray(P, np.float64).reshape(-1, 3)
            ok = (c > 1.0) & np.all(np.isfinite(P), axis=1)
            if stride > 1:
                ok &= _sample_mask(H, W, stride)
            keep = np.flatnonzero(ok)
            flats.append(offsets[v] + keep)
            pts.append(P[keep])
            # Each sample stands for stride^2 pixels: the objective keeps its scale.
            wts.append(np.log(c[keep]) * (stride * stride) / (H * W))
            count += len(keep)
        starts.append(starts[-1] + count)

    def t(x, dt):
        return torch.as_tensor(np.concatenate(x), dtype=dt, device=device)

    return _Terms(t(flats, torch.long), t(pts, dtype), t(wts, dtype), starts)


class _Params(torch.nn.Module):
    def __init__(self, log_depth, q_wfc, t_wfc, log_focal, q_pair, t_pair, logs_pair, *, optimize_focal: bool):
        super().__init__()
        self.log_depth = torch.nn.Parameter(log_depth)
        self.q_wfc = torch.nn.Parameter(q_wfc)
        self.t_wfc = torch.nn.Parameter(t_wfc)
        self.log_focal = torch.nn.Parameter(log_focal, requires_grad=optimize_focal)
        self.q_pair = torch.nn.Parameter(q_pair)
        self.t_pair = torch.nn.Parameter(t_pair)
        self.logs_pair = torch.nn.Parameter(logs_pair)


@dataclass
class _Grid:
    """Pixel grids of all views, concatenated like `log_depth` (torch tensors)."""

    du: torch.Tensor  # (P,) u - cx
    dv: torch.Tensor  # (P,) v - cy
    focal_of_pixel: torch.Tensor  # (P,) long, index into log_focal
    view_start: list[int]  # pixels of view n: view_start[n]:view_start[n + 1]


def world_points(params: _Params, grid: _Grid) -> torch.Tensor:
    """(P, 3) every pixel of every view back-projected into the world."""
    depth = torch.exp(params.log_depth)
    f = torch.exp(params.log_focal)[grid.focal_of_pixel]
    x_cam = torch.stack([grid.du / f * depth, grid.dv / f * depth, depth], dim=-1)
    R = R_from_quat(params.q_wfc)
    parts = [x_cam[a:b] @ R[n].T + params.t_wfc[n]
             for n, (a, b) in enumerate(zip(grid.view_start[:-1], grid.view_start[1:], strict=True))]
    return torch.cat(parts)


def alignment_loss(params: _Params, terms: _Terms, grid: _Grid, *, pinned_scale: float) -> torch.Tensor:
    """The DUSt3R objective (module docstring), vectorised over pixels, looped over views and pairs."""
    x_world = world_points(params, grid)[terms.flat]
    logs = params.logs_pair - params.logs_pair.mean() + math.log(pinned_scale)
    scale = torch.exp(logs)
    Rp = R_from_quat(params.q_pair)
    # A loop over pairs: measured 2x faster than gathering a rotation per term (its backward
    # scatter-adds M 3x3 gradients).
    st = terms.edge_start
    aligned = torch.cat([scale[e] * (terms.pred[st[e]:st[e + 1]] @ Rp[e].T) + params.t_pair[e]
                         for e in range(len(st) - 1)])
    return torch.sum(terms.weight * torch.linalg.norm(x_world - aligned, dim=-1))


@dataclass
class _TermIndex:
    """The problem of `alignment_loss_and_grads` in numpy, components first (built once per optimisation).

    Terms are sorted by pair (`_Terms.edge_start`) and pixels by view (`_Grid.view_start`): each pair's
    and each view's rows are one contiguous run.
    """

    flat: np.ndarray  # (M,) pixel of each term
    pred: np.ndarray  # (3, M) float64 pair-frame points
    weight: np.ndarray  # (M,) float64
    edges: list[tuple[int, int]]  # terms of pair e: edges[e][0]:edges[e][1]
    views: list[tuple[int, int]]  # pixels of view n: views[n][0]:views[n][1]
    du: np.ndarray  # (P,) float64
    dv: np.ndarray  # (P,) float64
    focal_of_pixel: np.ndarray  # (P,)


def _term_index(terms: _Terms, grid: _Grid) -> _TermIndex:
    def np64(x):
        return x.detach().cpu().numpy().astype(np.float64)

    st, vs = terms.edge_start, grid.view_start
    return _TermIndex(terms.flat.cpu().numpy(), np.ascontiguousarray(np64(terms.pred).T), np64(terms.weight),
                      list(zip(st[:-1], st[1:], strict=True)), list(zip(vs[:-1], vs[1:], strict=True)),
                      np64(grid.du), np64(grid.dv), grid.focal_of_pixel.cpu().numpy())


def _R_from_quat_np(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, 3, 3) rotations of (K, 4) wxyz quaternions (normalised as `R_from_quat`), the unit quaternions
    and the norms."""
    nq = np.maximum(np.linalg.norm(q, axis=-1), 1e-12)
    w, x, y, z = (q / nq[:, None]).T
    R = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)
    return R.reshape(-1, 3, 3), np.stack([w, x, y, z], axis=-1), nq


def _quat_grad(G: np.ndarray, qu: np.ndarray, nq: np.ndarray) -> np.ndarray:
    """d loss / d q (K, 4) from d loss / d R (K, 3, 3) for R = R(q / |q|) (`_R_from_quat_np`)."""
    w, x, y, z = qu.T
    g = G.reshape(-1, 9).T
    gw = 2 * (-z * g[1] + y * g[2] + z * g[3] - x * g[5] - y * g[6] + x * g[7])
    gx = 2 * (y * g[1] + z * g[2] + y * g[3] - 2 * x * g[4] - w * g[5] + z * g[6] + w * g[7] - 2 * x * g[8])
    gy = 2 * (-2 * y * g[0] + x * g[1] + w * g[2] + x * g[3] + z * g[5] - w * g[6] + z * g[7] - 2 * y * g[8])
    gz = 2 * (-2 * z * g[0] - w * g[1] + x * g[2] + w * g[3] - 2 * z * g[4] + y * g[5] + x * g[6] + y * g[7])
    gu = np.stack([gw, gx, gy, gz], axis=-1)
    return (gu - qu * np.sum(qu * gu, axis=-1, keepdims=True)) / nq[:, None]


def alignment_loss_and_grads(params: _Params, index: _TermIndex, *, pinned_scale: float
                             ) -> tuple[float, dict[str, np.ndarray]]:
    """`alignment_loss` and its gradient with respect to every parameter, by the chain rule in numpy (float64).

    Autograd of `alignment_loss` (a loop over views and pairs: ~250 small ops and their backward per
    evaluation) cost ~14 ms per iteration on llff_like 12 views, nearly all operator overhead. Here
    arrays are (3, K), so every elementwise op runs over one long axis; each view and each pair is a
    contiguous run (one 3x3 product each); the only scatter is the per-pixel one (`np.bincount`).
    Same value and gradient up to round-off (tests: against autograd of `alignment_loss` in float64).

    Returns:
        (loss, {parameter name: float64 gradient}) for the parameters that require a gradient
        (reshape to the parameter's shape).
    """
    def np64(x):
        return x.detach().cpu().numpy().astype(np.float64)

    ix = index
    P = len(ix.du)
    R, qu, nq = _R_from_quat_np(np64(params.q_wfc))  # world_from_cam
    Rp, qpu, nqp = _R_from_quat_np(np64(params.q_pair))  # world_from_pair
    t_wfc, t_pair = np64(params.t_wfc), np64(params.t_pair)
    logs = np64(params.logs_pair)
    scale = np.exp(logs - logs.mean() + math.log(pinned_scale))
    depth = np.exp(np64(params.log_depth))
    log_focal = np64(params.log_focal)
    f = np.exp(log_focal)[ix.focal_of_pixel]
    x_cam = np.stack([ix.du / f * depth, ix.dv / f * depth, depth])  # (3, P)
    x_world = np.empty_like(x_cam)
    for n, (a, b) in enumerate(ix.views):
        x_world[:, a:b] = R[n] @ x_cam[:, a:b] + t_wfc[n][:, None]
    r = np.take(x_world, ix.flat, axis=1)  # becomes x_world - aligned, (3, M)
    for e, (a, b) in enumerate(ix.edges):
        r[:, a:b] -= (scale[e] * Rp[e]) @ ix.pred[:, a:b] + t_pair[e][:, None]
    norm = np.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    loss = float(np.dot(ix.weight, norm))
    # d loss / d r; zero where the residual is zero (as autograd's norm backward).
    pos = norm > 0
    g = r * np.where(pos, ix.weight / np.where(pos, norm, 1.0), 0.0)
    # Pair side: aligned = s R_p pred + t_p enters with a minus sign.
    GP = np.stack([g[:, a:b] @ ix.pred[:, a:b].T for a, b in ix.edges])  # (E, 3, 3) sum of g pred^T
    grads = {"t_pair": -np.stack([g[:, a:b].sum(axis=1) for a, b in ix.edges])}
    grads["q_pair"] = _quat_grad(-GP * scale[:, None, None], qpu, nqp)
    ds = -np.einsum("eij,eij->e", Rp, GP) * scale  # d loss / d s, times ds / d logs' exponent
    grads["logs_pair"] = ds - ds.mean()
    # Camera side: scatter the terms onto their pixels, then per view.
    g_world = np.stack([np.bincount(ix.flat, weights=g[k], minlength=P) for k in range(3)])  # (3, P)
    g_cam = np.empty_like(g_world)
    dR = np.empty_like(R)
    for n, (a, b) in enumerate(ix.views):
        g_cam[:, a:b] = R[n].T @ g_world[:, a:b]
        dR[n] = g_world[:, a:b] @ x_cam[:, a:b].T
    grads["t_wfc"] = np.stack([g_world[:, a:b].sum(axis=1) for a, b in ix.views])
    grads["q_wfc"] = _quat_grad(dR, qu, nq)
    gxy = g_cam[0] * x_cam[0] + g_cam[1] * x_cam[1]
    grads["log_depth"] = gxy + g_cam[2] * x_cam[2]  # every component of x_cam is proportional to depth
    if params.log_focal.requires_grad:  # x, y scale with 1 / f
        grads["log_focal"] = -np.bincount(ix.focal_of_pixel, weights=gxy, minlength=len(log_focal))
    return loss, grads


def alignment_loss_reference(preds: Sequence[PairPrediction], *, cam_from_world: np.ndarray, focal_px: np.ndarray,
                             depth: Sequence[np.ndarray], pair_sim: Sequence[tuple[float, np.ndarray, np.ndarray]],
                             pinned_scale: float) -> float:
    """Slow, obvious float64 evaluation of the objective with loops (the tests' reference).

    `pair_sim[e] = (s, R, t)` maps pair e's frame to the world before the scale
    renormalisation (which this function applies).
    """
    mean_log = np.mean([math.log(s) for s, _, _ in pair_sim])
    total = 0.0
    for e, p in enumerate(preds):
        s, Rp, tp = pair_sim[e]
        s = math.exp(math.log(s) - mean_log) * pinned_scale
        for v, P, C in ((p.i, p.pts_i, p.conf_i), (p.j, p.pts_j, p.conf_j)):
            H, W = P.shape[:2]
            R, t = cam_from_world[v][:, :3], cam_from_world[v][:, 3]
            rays = pixel_rays(H, W, float(focal_px[v]))
            for r in range(H):
                for c in range(W):
                    if C[r, c] <= 1.0:
                        continue
                    x_cam = rays[r, c] * depth[v][r, c]
                    x_world = R.T @ (x_cam - t)
                    aligned = s * Rp @ P[r, c] + tp
                    total += math.log(C[r, c]) / (H * W) * np.linalg.norm(x_world - aligned)
    return total


class Adam:
    """Plain Adam (Kingma & Ba) with bias correction, as `torch.optim.Adam` computes it.

    Written out because the first `torch.optim` step imports torch.distributed
    (measured 25-40 s per process on the shared test machine, where bytecode
    caching is disabled), which dominated small alignments.
    """

    def __init__(self, params: list[torch.Tensor], *, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.params = params
        self.b1, self.b2 = betas
        self.eps = eps
        self.t = 0
        self.m = [torch.zeros_like(p) for p in params]
        self.v = [torch.zeros_like(p) for p in params]

    @torch.no_grad()
    def step(self, lr: float) -> None:
        self.t += 1
        c1 = 1 - self.b1**self.t
        c2 = 1 - self.b2**self.t
        for p, m, v in zip(self.params, self.m, self.v, strict=True):
            if p.grad is None:
                continue
            m.mul_(self.b1).add_(p.grad, alpha=1 - self.b1)
            v.mul_(self.b2).addcmul_(p.grad, p.grad, value=1 - self.b2)
            p.addcdiv_(m, (v / c2).sqrt_().add_(self.eps), value=-lr / c1)


