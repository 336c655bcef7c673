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
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from mvgeo.align.alignment_objective import (
    Adam,
    _build_terms,
    _Grid,
    _Params,
    _sample_mask,
    _term_index,
    _Terms,
    alignment_loss,
    alignment_loss_and_grads,
)
from mvgeo.align.graph import components, maximum_spanning_tree
from mvgeo.align.pairs import PairPrediction
from mvgeo.align.pointmap_geometry import (
    PNP_REFINE_POINTS,
    AlignInit,
    pair_similarities,
    pixel_rays,
    weighted_umeyama,
)
from mvgeo.align.pointmap_geometry import valid_pointmap_pixels as _valid
from mvgeo.common.deps import cv2
from mvgeo.common.errors import DegenerateGeometryError, InputError, UnposedViewsError
from mvgeo.common.progress import progress_bar
from mvgeo.common.threads import torch_threads
from mvgeo.pnp import sqpnp
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
            other pixels' log-depth receives the correction interpolated
            bilinearly between the sampled pixels around them (the poses and
            focals only see the samples).
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


# --------------------------------------------------------------------------- initialisation


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
        raise UnposedViewsError("not connected to the others by any pair whose pointmaps overlap", views=missing)
    cam_from_world = np.zeros((n, 3, 4))
    depth = []
    for v in range(n):
        H, W = sizes_hw[v]
        ok = _valid(conf_world[v], pts_world[v])
        rows, cols = np.nonzero(ok)
        if len(rows) < 6:
            raise UnposedViewsError(f"only {len(rows)} confident pixels, cannot estimate its pose", views=[v])
        uv_cv = np.stack([cols, rows], axis=1).astype(np.float64)  # OpenCV pixel centres at integers (= ours - 0.5)
        K_cv = np.array([[focal_init_px[v], 0, W / 2.0 - 0.5], [0, focal_init_px[v], H / 2.0 - 0.5], [0, 0, 1]])
        obj = pts_world[v][ok]
        okp, rvec, tvec = sqpnp(obj, uv_cv, K_cv)
        if not okp:
            raise UnposedViewsError("PnP on its chained pointmap failed", views=[v])
        sub = np.linspace(0, len(obj) - 1, min(len(obj), PNP_REFINE_POINTS)).round().astype(int)
        rvec, tvec = cv2.solvePnPRefineLM(obj[sub], uv_cv[sub], K_cv, None, rvec, tvec)
        R = cv2.Rodrigues(rvec)[0]
        cam_from_world[v] = np.concatenate([R, tvec.reshape(3, 1)], axis=1)
        z = (pts_world[v] @ R.T + tvec.reshape(1, 1, 3))[..., 2]
        med = float(np.median(z[ok]))
        if not med > 0:
            raise UnposedViewsError("its chained points lie behind the camera", views=[v])
        z = np.where(ok & (z > 1e-3 * med), z, med)
        depth.append(z)
    return AlignInit(cam_from_world, np.asarray(focal_init_px, np.float64).copy(), depth)


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

    if config.pixel_stride < 1:
        raise InputError(f"pixel_stride must be >= 1, got {config.pixel_stride}")
    stride = config.pixel_stride
    if init.pair_sim is None:  # fitted on the pixels the objective samples
        init = replace(init, pair_sim=pair_similarities(preds, sizes_hw, init.cam_from_world, init.depth,
                                                        init.focal_px, pixel_stride=stride))
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
    """Give every unsampled pixel the log-depth change interpolated bilinearly between the sampled pixels
    around it (`_sample_mask`'s grid); beyond the outermost samples the nearest one's."""
    delta = delta.copy()
    for v, (H, W) in enumerate(sizes_hw):
        d = delta[offsets[v]:offsets[v] + H * W].reshape(H, W)
        sub = d[stride // 2::stride, stride // 2::stride]
        # Fractional sample index of every row and column, clamped to the samples' range.
        fy = np.clip((np.arange(H) - stride // 2) / stride, 0, sub.shape[0] - 1)
        fx = np.clip((np.arange(W) - stride // 2) / stride, 0, sub.shape[1] - 1)
        y0, x0 = np.floor(fy).astype(int), np.floor(fx).astype(int)
        y1, x1 = np.minimum(y0 + 1, sub.shape[0] - 1), np.minimum(x0 + 1, sub.shape[1] - 1)
        wy, wx = (fy - y0)[:, None], (fx - x0)[None, :]
        top = sub[y0][:, x0] * (1 - wx) + sub[y0][:, x1] * wx
        bottom = sub[y1][:, x0] * (1 - wx) + sub[y1][:, x1] * wx
        delta[offsets[v]:offsets[v] + H * W] = (top * (1 - wy) + bottom * wy).reshape(-1)
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
        adam = Adam(trainable, betas=(0.9, 0.9))
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
