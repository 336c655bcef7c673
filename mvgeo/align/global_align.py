"""DUSt3R's global alignment of pairwise pointmaps, in torch.

Unknowns (float32 by default, CPU unless the inputs say otherwise):

- per view n: a log-depth map `log_depth[n]: (H_n, W_n)`, a pose
  `world_from_cam[n]` as an (unnormalised) wxyz quaternion and a translation,
  and a log-focal (one shared log-focal with `shared_focal=True`);
- per pair e = (i, j): a similarity `world_from_pair[e]` (quaternion,
  translation, log-scale) that maps the pair's pointmaps (camera-i frame) into
  the world.

Objective (DUSt3R eq. 5, Euclidean norm, not squared):

    L = sum_e sum_{v in {i, j}} sum_p  log(conf_v^e[p]) * || X_v[p] - sigma_e * P_e X_v^e[p] || / (H_v W_v)

where `X_v[p]` is pixel p of view v back-projected with its depth, focal and
pose. The pair scales are renormalised so that their geometric mean is
`pinned_scale` (the scene cannot collapse to a point). Pixels with conf == 1
have zero weight and are skipped. The principal point stays at the image
centre.

Initialisation: a maximum spanning tree over pair scores, chaining views with
confidence-weighted Procrustes with scale (Umeyama), then each view's pose by
PnP on its chained pointmap, depth from that pose, and each pair's similarity
by Procrustes against the chained points.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from mvgeo.align.graph import components, maximum_spanning_tree
from mvgeo.align.pairs import PairPrediction
from mvgeo.align.pointmap_geometry import (
    AlignInit,
    pair_similarities,
    pixel_rays,
    weighted_umeyama,
)
from mvgeo.align.pointmap_geometry import valid_pointmap_pixels as _valid
from mvgeo.common.deps import cv2
from mvgeo.common.errors import DegenerateGeometryError, InputError
from mvgeo.common.progress import progress_bar
from mvgeo.common.threads import torch_threads
from mvgeo.transforms import quat_from_R
from mvgeo.transforms_torch import R_from_quat

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GlobalAlignConfig:
    """Options of the global alignment (defaults as DUSt3R/InstantSplat).

    Attributes:
        iters: Adam iterations (0: initialisation only).
        lr: base learning rate.
        lr_min: final learning rate of the cosine schedule.
        shared_focal: one focal for all views (InstantSplat's focal averaging);
            requires all views to have the same pointmap size.
        optimize_focal: False keeps the focal lengths at their initial values
            (known intrinsics).
        pinned_scale: geometric mean of the pair scales.
        dtype: torch dtype of the optimisation (float32; float64 for tests).
        device: torch device ("cpu" by default).
        torch_threads: intra-op CPU threads during the optimisation (restored
            afterwards); 0 keeps torch's setting. The default 1 is deliberate:
            the work is many small ops, and on a shared 2-core machine two
            threads were measured ~40x slower than one (spin-waiting threads).
        pixel_stride: only pixels on every `pixel_stride`-th row and column
            enter the objective (cost / stride^2); after the optimisation the
            other pixels' log-depth receives the correction of their nearest
            sampled pixel (the poses and focals only see the samples).
        init: "procrustes" (DUSt3R: chain the pairs' pointmaps along the maximum
            spanning tree with weighted Procrustes, then PnP per view) or
            "pair_poses" (`mvgeo.align.pose_chain`: chain each tree pair's own
            relative pose, scale from the shared view's depth ratio).
    """

    iters: int = 300
    lr: float = 0.01
    lr_min: float = 1e-6
    shared_focal: bool = False
    optimize_focal: bool = True
    pinned_scale: float = 1.0
    dtype: torch.dtype = torch.float32
    device: str = "cpu"
    torch_threads: int = 1
    pixel_stride: int = 1
    init: str = "procrustes"


@dataclass
class GlobalAlignResult:
    """Output of `global_align` (numpy, float64 geometry).

    Attributes:
        cam_from_world: (N, 3, 4) poses.
        focal_px: (N,) focals in pixels of each view's pointmap grid.
        depth: list of (H_n, W_n) z-depth maps.
        pts_world: list of (H_n, W_n, 3) dense points in the world frame.
        conf: list of (H_n, W_n) per-pixel confidence (max over the pairs that see it).
        loss_history: loss per iteration (index 0: after initialisation).
        init_loss: loss after initialisation.
        final_loss: loss after optimisation.
    """

    cam_from_world: np.ndarray
    focal_px: np.ndarray
    depth: list[np.ndarray]
    pts_world: list[np.ndarray]
    conf: list[np.ndarray]
    loss_history: list[float] = field(default_factory=list)
    init_loss: float = float("nan")
    final_loss: float = float("nan")


# --------------------------------------------------------------------------- the problem


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


# --------------------------------------------------------------------------- initialisation


#: The LM refinement of each view's initial PnP pose uses at most this many pixels, evenly spread
#: (all 12k of a 128 x 96 pointmap took ~18 ms per view; 3000 ~4 ms; it only starts the alignment).
PNP_REFINE_POINTS = 3000


def init_from_spanning_tree(preds: Sequence[PairPrediction], sizes_hw: Sequence[tuple[int, int]], *,
                            focal_init_px: np.ndarray) -> AlignInit:
    """DUSt3R's MST initialisation (see the module docstring).

    Args:
        preds: the pair predictions (a connected graph over all views).
        sizes_hw: (H_n, W_n) per view.
        focal_init_px: (N,) focal per view used for PnP.

    Raises:
        DegenerateGeometryError: a view could not be chained or posed.
    """
    n = len(sizes_hw)
    edges = [(p.i, p.j) for p in preds]
    scores = [max(p.score, 1e-6) for p in preds]
    order = maximum_spanning_tree(n, edges, scores)
    pts_world: dict[int, np.ndarray] = {}
    conf_world: dict[int, np.ndarray] = {}
    first = preds[order[0]]
    pts_world[first.i], conf_world[first.i] = first.pts_i.astype(np.float64), first.conf_i
    pts_world[first.j], conf_world[first.j] = first.pts_j.astype(np.float64), first.conf_j
    # Prim's algorithm = the maximum spanning tree grown from its strongest edge; an edge whose
    # Procrustes is degenerate (too little confident overlap) is skipped for the next best one.
    bad: set[int] = set()
    while True:
        frontier = sorted((k for k, p in enumerate(preds) if k not in bad
                           and ((p.i in pts_world) != (p.j in pts_world))), key=lambda k: -scores[k])
        if not frontier:
            break
        for k in frontier:
            p = preds[k]
            known, P_known, C_known, new, P_new, C_new = (
                (p.i, p.pts_i, p.conf_i, p.j, p.pts_j, p.conf_j) if p.i in pts_world
                else (p.j, p.pts_j, p.conf_j, p.i, p.pts_i, p.conf_i))
            ok = _valid(C_known, P_known) & _valid(conf_world[known], pts_world[known])
            w = np.log(C_known[ok]) * np.log(conf_world[known][ok])
            try:
                s, R, t = weighted_umeyama(P_known[ok].astype(np.float64), pts_world[known][ok], w)
            except DegenerateGeometryError:
                bad.add(k)
                continue
            pts_world[new] = s * P_new.astype(np.float64) @ R.T + t
            conf_world[new] = C_new
            break
    missing = [v for v in range(n) if v not in pts_world]
    if missing:
        raise DegenerateGeometryError(f"views {missing} are not connected to the others by any pair")
    cam_from_world = np.zeros((n, 3, 4))
    depth = []
    for v in range(n):
        H, W = sizes_hw[v]
        ok = _valid(conf_world[v], pts_world[v])
        rows, cols = np.nonzero(ok)
        if len(rows) < 6:
            raise DegenerateGeometryError(f"view {v}: only {len(rows)} confident pixels, cannot estimate its pose")
        uv_cv = np.stack([cols, rows], axis=1).astype(np.float64)  # OpenCV pixel centres at integers (= ours - 0.5)
        K_cv = np.array([[focal_init_px[v], 0, W / 2.0 - 0.5], [0, focal_init_px[v], H / 2.0 - 0.5], [0, 0, 1]])
        obj = pts_world[v][ok]
        okp, rvec, tvec = cv2.solvePnP(obj, uv_cv, K_cv, None, flags=cv2.SOLVEPNP_SQPNP)
        if not okp:
            raise DegenerateGeometryError(f"view {v}: PnP on its chained pointmap failed")
        sub = np.linspace(0, len(obj) - 1, min(len(obj), PNP_REFINE_POINTS)).round().astype(int)
        rvec, tvec = cv2.solvePnPRefineLM(obj[sub], uv_cv[sub], K_cv, None, rvec, tvec)
        R = cv2.Rodrigues(rvec)[0]
        cam_from_world[v] = np.concatenate([R, tvec.reshape(3, 1)], axis=1)
        z = (pts_world[v] @ R.T + tvec.reshape(1, 1, 3))[..., 2]
        med = float(np.median(z[ok]))
        if not med > 0:
            raise DegenerateGeometryError(f"view {v}: its chained points lie behind the camera")
        z = np.where(ok & (z > 1e-3 * med), z, med)
        depth.append(z)
    return AlignInit(cam_from_world, np.asarray(focal_init_px, np.float64).copy(), depth,
                     pair_similarities(preds, sizes_hw, cam_from_world, depth, focal_init_px))


# --------------------------------------------------------------------------- driver


def global_align(preds: Sequence[PairPrediction], sizes_hw: Sequence[tuple[int, int]], *,
                 config: GlobalAlignConfig = GlobalAlignConfig(), focal_init_px: np.ndarray | None = None,
                 init: AlignInit | None = None) -> GlobalAlignResult:
    """Recover poses, focals and dense depth from pairwise pointmaps.

    Args:
        preds: pair predictions; together they must connect all views.
        sizes_hw: (H_n, W_n) of each view's pointmap grid.
        config: options.
        focal_init_px: (N,) initial (or known, with `optimize_focal=False`)
            focals; default: per view, the median of the pairs' estimates.
        init: precomputed initialisation (default: `init_from_spanning_tree`).

    Returns:
        `GlobalAlignResult` (the world frame is arbitrary, scale set by `pinned_scale`).

    Raises:
        DegenerateGeometryError: disconnected views or failed initialisation.
        InputError: no pairs, or `shared_focal` with views of different sizes.
    """
    n = len(sizes_hw)
    if not preds:
        raise InputError("global alignment needs at least one pair prediction")
    comps = components(n, [(p.i, p.j) for p in preds])
    if len(comps) > 1:
        raise DegenerateGeometryError(
            "the pair graph is disconnected: " + "; ".join(f"group {k}: views {c}" for k, c in enumerate(comps)))
    if config.shared_focal and len(set(map(tuple, sizes_hw))) > 1:
        raise InputError("shared_focal needs all views at the same pointmap size")
    if focal_init_px is None:
        focal_init_px = focal_estimates(preds, n)
        if config.shared_focal:
            focal_init_px = np.full(n, float(np.exp(np.mean(np.log(focal_init_px)))))
    focal_init_px = np.asarray(focal_init_px, np.float64)
    if init is None and config.init == "pair_poses":
        from mvgeo.align.pose_chain import init_from_pair_poses

        init = init_from_pair_poses(preds, sizes_hw, focal_init_px=focal_init_px)
    elif init is None:
        if config.init != "procrustes":
            raise InputError(f"unknown initialisation {config.init!r}", fix="use 'procrustes' or 'pair_poses'")
        init = init_from_spanning_tree(preds, sizes_hw, focal_init_px=focal_init_px)

    dev, dt = torch.device(config.device), config.dtype
    # Renormalise the world so that the pair scales' geometric mean is already pinned.
    gm = math.exp(np.mean([math.log(s) for s, _, _ in init.pair_sim]))
    c = config.pinned_scale / gm
    log_depth = torch.as_tensor(np.concatenate([np.log(d * c).reshape(-1) for d in init.depth]), dtype=dt, device=dev)
    offsets = np.concatenate([[0], np.cumsum([h * w for h, w in sizes_hw])[:-1]])
    world_from_cam_R = np.transpose(init.cam_from_world[:, :, :3], (0, 2, 1))
    world_from_cam_t = -np.einsum("nij,nj->ni", world_from_cam_R, init.cam_from_world[:, :, 3]) * c
    q_pair = quat_from_R(np.stack([R for _, R, _ in init.pair_sim]))
    t_pair = np.stack([t for _, _, t in init.pair_sim]) * c
    logs_pair = np.log([s for s, _, _ in init.pair_sim])
    if config.shared_focal:
        log_focal = np.array([np.mean(np.log(init.focal_px))])
        focal_index = np.zeros(n, dtype=np.int64)
    else:
        log_focal = np.log(init.focal_px)
        focal_index = np.arange(n)
    T = lambda x: torch.as_tensor(np.asarray(x), dtype=dt, device=dev)  # noqa: E731
    params = _Params(log_depth, T(quat_from_R(world_from_cam_R)), T(world_from_cam_t), T(log_focal),
                     T(q_pair), T(t_pair), T(logs_pair), optimize_focal=config.optimize_focal)
    if config.pixel_stride < 1:
        raise InputError(f"pixel_stride must be >= 1, got {config.pixel_stride}")
    stride = config.pixel_stride
    terms = _build_terms(preds, sizes_hw, offsets, dt, dev, stride=stride)
    n_full = int(offsets[-1] + sizes_hw[-1][0] * sizes_hw[-1][1])
    # With a stride, only the sampled pixels are unknowns: every tensor has the samples' size.
    if stride > 1:
        sampled = np.concatenate([_sample_mask(h, w, stride) for h, w in sizes_hw])
    else:
        sampled = np.ones(n_full, bool)
    sidx = np.flatnonzero(sampled)
    to_sample = np.full(n_full, -1, np.int64)
    to_sample[sidx] = np.arange(len(sidx))
    terms.flat = torch.as_tensor(to_sample[terms.flat.cpu().numpy()], dtype=torch.long, device=dev)
    log_depth_full = params.log_depth.detach().clone()
    params.log_depth = torch.nn.Parameter(log_depth_full[torch.as_tensor(sidx, device=dev)].clone())
    du = np.concatenate([(pixel_rays(h, w, 1.0)[..., 0]).reshape(-1) for h, w in sizes_hw])[sidx]
    dv = np.concatenate([(pixel_rays(h, w, 1.0)[..., 1]).reshape(-1) for h, w in sizes_hw])[sidx]
    fpix = np.concatenate([np.full(h * w, focal_index[n]) for n, (h, w) in enumerate(sizes_hw)])[sidx]
    view_end = np.cumsum([np.count_nonzero(sampled[o:o + h * w]) for o, (h, w) in zip(offsets, sizes_hw,
                                                                                        strict=True)])
    grid = _Grid(T(du), T(dv), torch.as_tensor(fpix, dtype=torch.long, device=dev),
                 [0] + [int(x) for x in view_end])

    with torch_threads(config.torch_threads if config.torch_threads > 0 else None):
        history = _optimise(params, terms, grid, config)
    _log.info("global alignment: loss %.5g -> %.5g over %d iterations", history[0], history[-1], config.iters)
    with torch.no_grad():
        delta = np.zeros(n_full)
        delta[sidx] = (params.log_depth - log_depth_full[torch.as_tensor(sidx, device=dev)]).double().cpu().numpy()
        if stride > 1:
            delta = _spread(delta, sizes_hw, offsets, stride)
        params.log_depth = torch.nn.Parameter(log_depth_full + torch.as_tensor(delta, dtype=dt, device=dev))
    return _collect(params, preds, sizes_hw, focal_index, offsets, history[0], history)


def _spread(delta: np.ndarray, sizes_hw, offsets, stride: int) -> np.ndarray:
    """Give every unsampled pixel the log-depth change of its nearest sampled pixel (block copy)."""
    delta = delta.copy()
    for v, (H, W) in enumerate(sizes_hw):
        d = delta[offsets[v]:offsets[v] + H * W].reshape(H, W)
        sub = d[stride // 2::stride, stride // 2::stride]
        full = np.repeat(np.repeat(sub, stride, axis=0), stride, axis=1)
        # Blocks are centred on their sample; pad the last ones by edge replication.
        full = np.pad(full, ((0, max(0, H - full.shape[0])), (0, max(0, W - full.shape[1]))), mode="edge")
        delta[offsets[v]:offsets[v] + H * W] = full[:H, :W].reshape(-1)
    return delta


def _optimise(params: _Params, terms: _Terms, grid: _Grid, config: GlobalAlignConfig) -> list[float]:
    """Adam with a cosine schedule; returns the loss history (first: initial, last: final)."""
    kw = dict(pinned_scale=config.pinned_scale)
    with torch.no_grad():
        init_loss = float(alignment_loss(params, terms, grid, **kw))
    history = [init_loss]
    named = [(k, p) for k, p in params.named_parameters() if p.requires_grad]
    trainable = [p for _, p in named]
    if config.iters > 0:
        adam = _Adam(trainable, betas=(0.9, 0.9))
        # The chain-rule gradient (numpy) on CPU; autograd of `alignment_loss` elsewhere.
        index = _term_index(terms, grid) if terms.flat.device.type == "cpu" else None
        with progress_bar(desc="global alignment", total=config.iters) as bar:
            for it in range(config.iters):
                frac = it / max(config.iters - 1, 1)
                lr = config.lr_min + (config.lr - config.lr_min) * 0.5 * (1 + math.cos(math.pi * frac))
                if index is not None:
                    loss, grads = alignment_loss_and_grads(params, index, **kw)
                    for k, p in named:
                        p.grad = torch.as_tensor(grads[k], dtype=p.dtype).reshape(p.shape)
                else:
                    for p in trainable:
                        p.grad = None
                    loss_t = alignment_loss(params, terms, grid, **kw)
                    loss_t.backward()
                    loss = float(loss_t.detach())
                if not math.isfinite(loss):
                    raise DegenerateGeometryError(f"global alignment diverged (loss {loss}) at iteration {it}")
                adam.step(lr)
                history.append(loss)
                bar.update(1)
                if it % 20 == 0:
                    bar.set_postfix(loss=f"{history[-1]:.4g}")
        with torch.no_grad():
            history.append(float(alignment_loss(params, terms, grid, **kw)))
    return history


class _Adam:
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


def focal_estimates(preds: Sequence[PairPrediction], n: int) -> np.ndarray:
    """(N,) median over pairs of each view's focal estimate (nan-free; raises if a view has none)."""
    per_view: list[list[float]] = [[] for _ in range(n)]
    for p in preds:
        if np.isfinite(p.focal_i_px) and p.focal_i_px > 0:
            per_view[p.i].append(p.focal_i_px)
        if p.focal_j_px is not None and np.isfinite(p.focal_j_px) and p.focal_j_px > 0:
            per_view[p.j].append(p.focal_j_px)
    allf = [f for fs in per_view for f in fs]
    if not allf:
        raise DegenerateGeometryError("no pair produced a focal estimate")
    return np.array([np.median(fs) if fs else np.median(allf) for fs in per_view])


def _collect(params: _Params, preds, sizes_hw, focal_index, offsets, init_loss, history) -> GlobalAlignResult:
    with torch.no_grad():
        R_wfc = R_from_quat(params.q_wfc).double().cpu().numpy()
        t_wfc = params.t_wfc.double().cpu().numpy()
        focal = np.exp(params.log_focal.double().cpu().numpy())[focal_index]
        log_depth = params.log_depth.double().cpu().numpy()
    n = len(sizes_hw)
    cam_from_world = np.zeros((n, 3, 4))
    depth, pts_world, conf = [], [], []
    for v in range(n):
        H, W = sizes_hw[v]
        R = R_wfc[v].T
        cam_from_world[v] = np.concatenate([R, (-R @ t_wfc[v]).reshape(3, 1)], axis=1)
        d = np.exp(log_depth[offsets[v]:offsets[v] + H * W]).reshape(H, W)
        depth.append(d)
        pts_world.append((pixel_rays(H, W, float(focal[v])) * d[..., None]) @ R_wfc[v].T + t_wfc[v])
        conf.append(np.ones((H, W)))
    for p in preds:
        conf[p.i] = np.maximum(conf[p.i], p.conf_i)
        conf[p.j] = np.maximum(conf[p.j], p.conf_j)
    return GlobalAlignResult(cam_from_world, focal, depth, pts_world, conf, history, init_loss, history[-1])
