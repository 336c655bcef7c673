"""Adaptive density control of 3DGS (clone / split / prune); off by default for sparse views.

State is explicit (`DensifyState`), the model and optimizer are rebuilt with
index maps so Adam moments follow the Gaussians they belong to.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mvgeo.transforms_torch import R_from_quat
from splat.gaussian_model import PARAM_NAMES, GaussianModel


@dataclass
class DensifyConfig:
    """3DGS's defaults, rescaled to ~1000-iteration schedules.

    Attributes:
        start_iter, stop_iter, every: densify at iterations in [start, stop) divisible by `every`.
        grad_threshold: mean screen-space gradient norm of the means (in NDC-like units:
            pixel gradient times half the larger image side), above which a Gaussian is densified.
        percent_dense: Gaussians whose largest scale exceeds this fraction of the scene extent are split,
            the others cloned.
        prune_opacity: Gaussians below this opacity are removed.
        max_gaussians: never grow beyond this count.
    """

    start_iter: int = 100
    stop_iter: int = 600
    every: int = 100
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    max_gaussians: int = 1_000_000


@dataclass
class DensifyState:
    """Running statistics per Gaussian: accumulated gradient norm and visibility count."""

    grad_accum: torch.Tensor
    count: torch.Tensor

    @classmethod
    def zeros(cls, n: int, device) -> DensifyState:
        return cls(torch.zeros(n, device=device), torch.zeros(n, device=device))


def accumulate(state: DensifyState, means2d_grad: torch.Tensor, visible: torch.Tensor, width: int, height: int):
    """Add this view's screen-space gradient norms (in place)."""
    g = means2d_grad.detach().norm(dim=-1) * 0.5 * max(width, height)
    state.grad_accum += torch.where(visible, g, torch.zeros_like(g))
    state.count += visible.to(state.count.dtype)


def densify_and_prune(model: GaussianModel, optimizer: torch.optim.Adam, state: DensifyState,
                      config: DensifyConfig, scene_extent: float, generator: torch.Generator
                      ) -> tuple[GaussianModel, DensifyState]:
    """One densification step; returns the new model (the optimizer's param groups are updated in place)."""
    with torch.no_grad():
        avg = state.grad_accum / state.count.clamp(min=1)
        big_grad = avg > config.grad_threshold
        max_scale = model.scales.max(dim=-1).values
        small = max_scale <= config.percent_dense * scene_extent
        room = max(config.max_gaussians - model.num_gaussians, 0)
        clone_idx = torch.nonzero(big_grad & small).reshape(-1)[:room]
        split_idx = torch.nonzero(big_grad & ~small).reshape(-1)[: max(room - clone_idx.numel(), 0) // 2]
        params = {k: v.detach() for k, v in model.params_dict().items()}
        # Split: two samples from each Gaussian, scales / 1.6 (3DGS); the parent is removed.
        if split_idx.numel():
            s = model.scales[split_idx].repeat(2, 1)
            noise = torch.randn(s.shape, generator=generator, dtype=s.dtype).to(s.device) * s
            R = R_from_quat(params["quats"][split_idx]).repeat(2, 1, 1)
            new_means = (R @ noise[..., None])[..., 0] + params["means"][split_idx].repeat(2, 1)
        keep = torch.ones(model.num_gaussians, dtype=torch.bool, device=params["means"].device)
        keep[split_idx] = False
        keep &= torch.sigmoid(params["opacity_logits"]) >= config.prune_opacity
        keep[clone_idx] = True
        src = torch.cat([torch.nonzero(keep).reshape(-1), clone_idx, split_idx.repeat(2)])
        new = {k: v[src].clone() for k, v in params.items()}
        if split_idx.numel():
            n_old = int(keep.sum()) + clone_idx.numel()
            new["means"][n_old:] = new_means
            new["log_scales"][n_old:] = torch.log(s / 1.6)
        new_model = GaussianModel(**new)
        # Adam moments follow their Gaussian; fresh copies start from zero moments as in 3DGS for splits.
        n_keep = int(keep.sum())
        for group in optimizer.param_groups:
            name = group["name"]
            if name not in PARAM_NAMES:
                continue
            old_p = group["params"][0]
            st = optimizer.state.pop(old_p, None)
            new_p = getattr(new_model, name)
            group["params"][0] = new_p
            if st:
                for key in ("exp_avg", "exp_avg_sq"):
                    moved = st[key][src].clone()
                    moved[n_keep:] = 0
                    st[key] = moved
                optimizer.state[new_p] = st
        return new_model, DensifyState.zeros(new_model.num_gaussians, params["means"].device)
