"""Round 2: fine-tune the N2V UNet so its outputs agree with the round-1 renders.

For view i the network gets the noisy photo ``noisy_i`` (optionally N2V-masked,
so that K-pass inference stays valid) and produces ``out_i``. The joint loss
(`joint_loss`, weights in `Round2Config`) has

- a **low-frequency** term, ``Charbonnier(blur(out_i), blur(noisy_i))``: the
  view keeps its own colours and shading (noise is zero-mean and is blurred
  away; the render may be slightly off in exposure or geometry);
- **detail** terms against the round-1 render ``render_i`` (multi-view
  consistent, noise-free): Charbonnier of the high-pass parts
  ``out - blur(out)`` vs ``render - blur(render)``, ``1 - SSIM(out, render)``,
  gradient consistency, and chroma consistency (Cb, Cr of YCbCr);
- optional total variation of ``out``.

The round-1 render is not trusted blindly: a splat trained for a few hundred
iterations is blurry or misregistered in places, and copying it there makes
round 2 worse than round 1 (measured on the demo scene before this change).
`render_trust_target` therefore builds the detail target per pixel as the
inverse-variance combination of the two estimates of the clean image that
round 2 has, the render and the round-1 output, with each one's local squared
error estimated from the noisy photo and the noise level alone (no clean
image, nothing tuned to a scene); see its docstring.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from denoise.filters import gaussian_blur
from denoise.fusion import fuse_with_observation
from denoise.images import images_to_tensors
from denoise.inference import MARGIN_PX, TILE_PX, predict_tiled
from denoise.losses import charbonnier, chroma_loss, gradient_loss, total_variation
from denoise.masking import mask_pixels
from denoise.model import N2VModel
from denoise.n2v import StepBatch, chunked_backward, lr_factor, weight_sharing_replicas
from denoise.noise_level import estimate_noise_sigma_robust
from denoise.parallel import group_size, one_thread_per_task, run_tasks
from denoise.patches import effective_patch_px, sample_patches
from mvgeo.common.errors import ConfigError, InputError
from mvgeo.common.progress import progress_bar
from mvgeo.image_metrics import ssim


@dataclass(frozen=True)
class Round2Config:
    """Round-2 fine-tuning options and loss weights (defaults documented per field).

    Attributes:
        w_low: low-frequency Charbonnier(blur(out), blur(noisy)) (1.0: the anchor to the photo).
        w_detail: Charbonnier between high-pass parts of out and render (1.0).
        w_ssim: ``1 - SSIM(out, render)`` (0.2, the 3DGS L1/SSIM balance).
        w_grad: gradient consistency with the render (0.5).
        w_chroma: chroma (CbCr) consistency with the render (0.5; renders have no chroma noise).
        w_tv: total variation of out (0: off; the render already supplies the smoothness).
        blur_sigma: Gaussian sigma (px) separating low and high frequencies (2.0).
        charbonnier_eps: Charbonnier epsilon in [0, 1] units (1e-3).
        steps, batch_size, patch_px, lr: fine-tuning schedule (Adam, cosine decay, no warm-up).
        mask_input: apply the model's N2V masking to the input (keeps the network usable with
            K-pass inference).
        loss: "joint" (the terms above) or "charbonnier" (Table 2 ablation: the joint loss
            replaced by ``Charbonnier(out, target)`` alone).
        trust_render: build the detail target with `render_trust_target` (True) or use the
            render as it is (False, the paper's literal recipe).
        guard: keep the round-1 network unless fine-tuning lowered the blind-spot (J-invariant)
            loss on the selected views (`blind_spot_loss`, the self-supervised estimate of the
            error against the clean images) by more than `guard_z` standard errors.
        guard_z: how many standard errors of the paired loss differences the gain must exceed
            (`guard_decision`; 0: any gain). 2: a fine-tuned network that changed nothing is
            not kept by chance (one-sided, about 2 %), so a round 2 that gains nothing
            measurable costs no second splat (`PipelineConfig.stop_when_unrefined`). On DTU
            scan24 (sigma 25/255) the fine-tuning lowered the loss by 1.2e-6 (1e-4 relative) and
            the rule with 0 kept it: the second round scored the same as the first and cost 244 s.
        guard_cells: how many of the 25 cells of `jinvariant_predict`'s 5x5 grid the guard
            scores (5: a fifth of the pixels, one cell in every grid row and column; 25: all).
            Both networks see the same cells and replacements, so the comparison is paired;
            at 504x378 a fifth still scores 1.4 million values on 12 views, and the guard
            costs 10 network passes per view instead of 50.
        batch_chunks: a step's batch split into this many chunks, each on one torch thread
            (`N2VConfig.batch_chunks`): the result depends on it, not on the machine's threads.
    """

    w_low: float = 1.0
    w_detail: float = 1.0
    w_ssim: float = 0.2
    w_grad: float = 0.5
    w_chroma: float = 0.5
    w_tv: float = 0.0
    blur_sigma: float = 2.0
    charbonnier_eps: float = 1e-3
    steps: int = 200
    batch_size: int = 8
    patch_px: int = 64
    lr: float = 2e-4
    mask_input: bool = True
    loss: Literal["joint", "charbonnier"] = "joint"
    trust_render: bool = True
    guard: bool = True
    guard_cells: int = 5
    guard_z: float = 2.0
    batch_chunks: int = 2

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name.startswith("w_") and not v >= 0:
                raise ConfigError(f"loss weight must be >= 0, got {v}", key=f.name)
        for key in ("steps", "batch_size", "patch_px"):
            if getattr(self, key) < 1:
                raise ConfigError(f"must be >= 1, got {getattr(self, key)}", key=key)
        if self.loss not in ("joint", "charbonnier"):
            raise ConfigError(f"unknown loss {self.loss!r}", key="loss", expected="'joint' or 'charbonnier'")
        if self.batch_chunks < 1:
            raise ConfigError(f"must be >= 1, got {self.batch_chunks}", key="batch_chunks")
        if not self.guard_z >= 0:
            raise ConfigError(f"must be >= 0, got {self.guard_z}", key="guard_z")
        if not 1 <= self.guard_cells <= JINVARIANT_STRIDE**2:
            raise ConfigError(f"must be in 1..{JINVARIANT_STRIDE**2}, got {self.guard_cells}", key="guard_cells")
        if not (self.lr > 0 and self.blur_sigma > 0 and self.charbonnier_eps > 0):
            raise ConfigError("lr, blur_sigma and charbonnier_eps must be > 0", key="lr")


@dataclass(frozen=True)
class Round2Terms:
    """The weighted total and the unweighted terms of `joint_loss` (scalars)."""

    total: Tensor
    low: Tensor
    detail: Tensor
    ssim: Tensor
    grad: Tensor
    chroma: Tensor
    tv: Tensor


def joint_loss(out: Tensor, noisy: Tensor, render: Tensor, config: Round2Config | None = None) -> Round2Terms:
    """The round-2 loss of a batch.

    Args:
        out: ``[B, 3, H, W]`` network output, ``[0, 1]`` units.
        noisy: ``[B, 3, H, W]`` the (unmasked) noisy input.
        render: ``[B, 3, H, W]`` the round-1 render of the same view.
        config: weights (default `Round2Config()`).

    With ``config.loss == "charbonnier"`` the total is ``Charbonnier(out, render)``
    alone (reported as `detail`; the other terms are 0).

    Returns:
        `Round2Terms`. SSIM uses the ``reflect`` border so that small patches count every pixel.
    """
    cfg = config or Round2Config()
    eps, s = cfg.charbonnier_eps, cfg.blur_sigma
    if cfg.loss == "charbonnier":
        c = charbonnier(out, render, eps=eps)
        zero = torch.zeros((), dtype=out.dtype, device=out.device)
        return Round2Terms(total=c, low=zero, detail=c, ssim=zero, grad=zero, chroma=zero, tv=zero)
    blur_out = gaussian_blur(out, sigma=s)
    low = charbonnier(blur_out, gaussian_blur(noisy, sigma=s), eps=eps)
    detail = charbonnier(out - blur_out, render - gaussian_blur(render, sigma=s), eps=eps)
    ssim_term = 1.0 - ssim(out, render, border="reflect")
    grad = gradient_loss(out, render)
    chroma = chroma_loss(out, render, eps=eps)
    tv = total_variation(out)
    total = (cfg.w_low * low + cfg.w_detail * detail + cfg.w_ssim * ssim_term + cfg.w_grad * grad
             + cfg.w_chroma * chroma + cfg.w_tv * tv)
    return Round2Terms(total=total, low=low, detail=detail, ssim=ssim_term, grad=grad, chroma=chroma, tv=tv)


#: Grid period of `jinvariant_predict`: each pass masks one cell of a 5x5 grid, 1/25 = 4% of the
#: pixels, the N2V training rate.
JINVARIANT_STRIDE = 5


def spread_cells(count: int, stride: int = JINVARIANT_STRIDE) -> list[tuple[int, int]]:
    """`count` cells ``(row % stride, col % stride)`` of the grid, spread out: the first `stride`
    form a Latin diagonal ``(i, 2i mod stride)``, so any `stride` of them hit every grid row and
    column once; later ones shift that diagonal."""
    order = [(i, (2 * i + j) % stride) for j in range(stride) for i in range(stride)]
    if not 1 <= count <= len(order):
        raise ValueError(f"count must be in 1..{len(order)}, got {count}")
    return order[:count]


def cell_mask(h: int, w: int, cells: Sequence[tuple[int, int]], *, stride: int = JINVARIANT_STRIDE,
              device: torch.device | str = "cpu") -> Tensor:
    """``[h, w]`` bool: the pixels with ``(row % stride, col % stride)`` in `cells`."""
    rows = torch.arange(h, device=device)[:, None] % stride
    cols = torch.arange(w, device=device)[None, :] % stride
    out = torch.zeros(h, w, dtype=torch.bool, device=device)
    for a, b in cells:
        out |= (rows == a % stride) & (cols == b % stride)
    return out


@torch.no_grad()
def jinvariant_predict(model: N2VModel, x: Tensor, *, stride: int = JINVARIANT_STRIDE,
                       cells: Sequence[tuple[int, int]] | None = None, generator: torch.Generator | None = None,
                       tile_px: int = TILE_PX, margin_px: int = MARGIN_PX) -> Tensor:
    """A prediction of every pixel that never saw that pixel's own value (J-invariant, Batson & Royer 2019).

    ``stride**2`` passes; pass ``(a, b)`` replaces the pixels with ``row % stride == a`` and
    ``col % stride == b`` by values taken from random *unmasked* positions of the same image
    (N2V's replacement, restricted so that no masked pixel's own value is anywhere in the
    input) and keeps the prediction at those pixels only. So the output at a pixel never
    depends on that pixel's value, and for noise independent across pixels
    ``E (y - f(y))^2 = sigma^2 + E (x - f(y))^2``: the prediction serves both the trust
    target and the guard. The default stride 5 masks 1/25 = 4% of the pixels per pass, the
    N2V training rate.

    Args:
        model: any `N2VModel`.
        x: ``[B, 3, H, W]``.
        stride: grid period in pixels (>= 2).
        cells: run only these passes ``(a, b)``; the other pixels are NaN. Every pass draws its
            replacements whether it runs or not, so with the same `generator` seed the
            predicted pixels equal the full prediction's bit for bit.
        generator: seeds the replacements.
    """
    if stride < 2:
        raise ValueError(f"stride must be >= 2, got {stride}")
    run = None if cells is None else {(int(a) % stride, int(b) % stride) for a, b in cells}
    model.unet.eval()
    b, c, h, w = x.shape
    out = torch.full_like(x, float("nan"))
    flat = x.reshape(b, c, h * w)

    def masked_prediction(p: tuple[Tensor, Tensor]) -> Tensor:
        mask, inp = p
        return predict_tiled(model, inp, tile_px=tile_px, margin_px=margin_px)[..., mask]

    # The passes' inputs are drawn in pass order (the draws do not depend on the threads) and predicted
    # `group_size` at a time (the cells are disjoint: each pass writes its own pixels).
    with one_thread_per_task():
        step = group_size(x)
        group: list[tuple[Tensor, Tensor]] = []
        cells_all = [(a, bb) for a in range(stride) for bb in range(stride)]
        for i, (a, bb) in enumerate(cells_all):
            mask = cell_mask(h, w, [(a, bb)], stride=stride, device=x.device)
            if bool(mask.any()):
                free = torch.nonzero(~mask.reshape(-1)).reshape(-1)
                pick = free[torch.randint(len(free), (b, h * w), generator=generator, device=x.device)]
                if run is None or (a, bb) in run:
                    repl = flat.gather(2, pick[:, None, :].expand(b, c, h * w)).reshape(b, c, h, w)
                    group.append((mask, torch.where(mask[None, None], repl, x)))
            if group and (len(group) == step or i == len(cells_all) - 1):
                for (m, _), values in zip(group, run_tasks(masked_prediction, group, device=x.device), strict=True):
                    out[..., m] = values
                group = []
    return out


def blind_spot_loss(model: N2VModel, noisy: Sequence[Tensor], *, seed: int = 0,
                    cells: Sequence[tuple[int, int]] | None = None) -> float:
    """Mean ``(y - f_J(y))^2`` over the views: the self-supervised estimate of ``sigma^2 + MSE`` vs clean.

    `noisy` holds ``[3, H, W]`` tensors; `f_J` is `jinvariant_predict` (stride
    `JINVARIANT_STRIDE`) with a fixed seed, so two models are compared on the same replacements;
    `cells` restricts the mean to those grid cells' pixels (the same for both models).
    """
    return _view_means(*blind_spot_blocks(model, noisy, seed=seed, cells=cells))


def blind_spot_blocks(model: N2VModel, noisy: Sequence[Tensor], *, seed: int = 0,
                      cells: Sequence[tuple[int, int]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`blind_spot_loss` per view and grid cell: ``(means, counts)``, both ``[views, cells]`` (all 25 cells
    when `cells` is None), the mean squared J-invariant residual of each cell's pixels and their number.
    Each cell is its own masking pass, so the blocks are the replicates `guard_decision` tests on."""
    cells = list(cells) if cells is not None else [(a, b) for a in range(JINVARIANT_STRIDE)
                                                   for b in range(JINVARIANT_STRIDE)]
    gen = torch.Generator(device=noisy[0].device).manual_seed(seed)
    means = np.zeros((len(noisy), len(cells)))
    counts = np.zeros((len(noisy), len(cells)))
    for v, y in enumerate(noisy):
        sq = ((jinvariant_predict(model, y[None], cells=cells, generator=gen) - y[None]) ** 2)[0]
        for c, cell in enumerate(cells):  # a NaN the network produces in a cell stays NaN
            m = cell_mask(*y.shape[-2:], [cell], device=y.device)
            means[v, c] = float(sq[:, m].mean())
            counts[v, c] = 3 * int(m.sum())
    return means, counts


def _view_means(means: np.ndarray, counts: np.ndarray) -> float:
    """The mean over views of each view's pixel-weighted mean over its cells."""
    return float(np.mean((means * counts).sum(axis=1) / counts.sum(axis=1)))


def guard_decision(before: np.ndarray, after: np.ndarray, z: float) -> tuple[bool, float, float]:
    """Whether the fine-tuned network's blind-spot loss is lower by more than `z` standard errors.

    A paired test on the blocks of `blind_spot_blocks` (both networks saw the same cells and
    replacements): ``d = before - after`` per block, gain ``mean(d)``, standard error
    ``std(d) / sqrt(blocks)``. With a single block the error cannot be estimated and any gain
    counts. A NaN anywhere keeps round 1.

    Returns:
        (keep the fine-tuned network, gain, standard error).
    """
    d = (np.asarray(before, float) - np.asarray(after, float)).ravel()
    gain = float(np.mean(d))
    se = float(np.std(d, ddof=1) / np.sqrt(d.size)) if d.size > 1 else 0.0
    keep = bool(np.isfinite(gain) and np.isfinite(se) and gain > z * se)
    return keep, gain, se


def trust_targets(model: N2VModel, noisy_t: Sequence[Tensor], render_t: Sequence[Tensor], *,
                  seed: int = 0, window_sigma_px: float = 2.0) -> tuple[list[Tensor], list[float]]:
    """`render_trust_target` per view, with the model's J-invariant prediction and a robust noise estimate.

    Returns:
        (targets ``[3, H, W]``, mean render weight per view).
    """
    gen = torch.Generator(device=noisy_t[0].device).manual_seed(seed)
    targets, weights = [], []
    for y, r in zip(noisy_t, render_t, strict=True):
        sigma = estimate_noise_sigma_robust(y.permute(1, 2, 0).cpu().numpy())
        mu = jinvariant_predict(model, y[None], generator=gen)
        tt = render_trust_target(y[None], mu, r[None], noise_sigma=sigma, window_sigma_px=window_sigma_px)
        targets.append(tt.target[0].clamp(0.0, 1.0))
        weights.append(float(tt.render_weight.mean()))
    return targets, weights


@dataclass
class Round2Report:
    """Diagnostics of `refine_round2` (JSON-able with `dataclasses.asdict`).

    Attributes:
        render_weight: mean render weight of the trust target per view (1.0 each without trust).
        loss_before, loss_after: `blind_spot_loss` of the round-1 and the fine-tuned network.
        loss_gain_se: standard error of their difference (`guard_decision`).
        reverted: the guard kept the round-1 network.
    """

    render_weight: list[float] = field(default_factory=list)
    loss_before: float = float("nan")
    loss_after: float = float("nan")
    loss_gain_se: float = float("nan")
    reverted: bool = False

    def to_json(self) -> dict[str, object]:
        """The report as JSON values (a stage summary's ``round2``); `from_json` reads it back."""
        return {"render_weight": [float(w) for w in self.render_weight], "loss_before": float(self.loss_before),
                "loss_after": float(self.loss_after), "loss_gain_se": float(self.loss_gain_se),
                "reverted": bool(self.reverted)}

    @classmethod
    def from_json(cls, d: Mapping[str, object]) -> Round2Report:
        """The report `to_json` wrote (a missing field keeps its default)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def kept_previous_because(self) -> str:
        """Why the guard kept the previous network, in words ("" when it did not)."""
        if not self.reverted:
            return ""
        by = (f", standard error of the difference {self.loss_gain_se:.2g}"
              if math.isfinite(self.loss_gain_se) else "")
        return (f"the fine-tuned network did not lower the blind-spot loss measurably ({self.loss_before:.6f} "
                f"before, {self.loss_after:.6f} after{by}), so the previous network and images were kept")


def refine_round2(model: N2VModel, noisy_images: Sequence[np.ndarray], renders: Sequence[np.ndarray],
                  config: Round2Config | None = None, *, seed: int = 0) -> tuple[N2VModel, Round2Report]:
    """Round 2 with its safeguards: trust target, fine-tuning, and the blind-spot-loss guard.

    Args: as `finetune_round2` (`model` is not modified; a fine-tuned copy is returned).

    Returns:
        (the model to denoise with: the fine-tuned copy, or `model` itself when the guard
        reverted; its `blind_spot` tells `denoise_images` how to fuse), `Round2Report`.
    """
    cfg = config or Round2Config()
    noisy_t, render_t = _check_views(noisy_images, renders, device=_model_device(model))
    report = Round2Report()
    if cfg.trust_render:
        targets, report.render_weight = trust_targets(model, noisy_t, render_t, seed=seed)
    else:
        targets, report.render_weight = render_t, [1.0] * len(render_t)
    tuned = copy.deepcopy(model)
    tuned.history = list(model.history)
    _finetune(tuned, noisy_t, targets, cfg, seed=seed)
    if cfg.guard:
        cells = spread_cells(cfg.guard_cells)
        before = blind_spot_blocks(model, noisy_t, seed=seed + 1, cells=cells)
        after = blind_spot_blocks(tuned, noisy_t, seed=seed + 1, cells=cells)
        report.loss_before, report.loss_after = _view_means(*before), _view_means(*after)
        keep, _, report.loss_gain_se = guard_decision(before[0], after[0], cfg.guard_z)
        if not keep:
            report.reverted = True
            return model, report
    return tuned, report


def _model_device(model: N2VModel) -> torch.device:
    return next(model.unet.parameters()).device


def _check_views(noisy_images: Sequence[np.ndarray], renders: Sequence[np.ndarray], *,
                 device: torch.device) -> tuple[list[Tensor], list[Tensor]]:
    """Validated ``[3, H, W]`` tensors of both lists, on `device` (the model's: training runs there)."""
    if len(noisy_images) != len(renders):
        raise InputError(f"{len(noisy_images)} noisy images but {len(renders)} renders",
                         fix="pass one render per noisy view, in the same order")
    noisy_t = images_to_tensors(noisy_images)
    render_t = images_to_tensors(renders)
    for i, (a, b) in enumerate(zip(noisy_t, render_t, strict=True)):
        if a.shape != b.shape:
            raise InputError(f"view {i}: noisy image is {tuple(a.shape[1:])} but render is {tuple(b.shape[1:])}",
                             fix="render at the photo's resolution")
    return [t.to(device) for t in noisy_t], [t.to(device) for t in render_t]


def finetune_round2(model: N2VModel, noisy_images: Sequence[np.ndarray], renders: Sequence[np.ndarray],
                    config: Round2Config | None = None, *, seed: int = 0) -> N2VModel:
    """Fine-tune `model` in place with the joint loss against `renders` as given and return it.

    The bare training loop (no trust target, no guard; `refine_round2` adds them).

    Args:
        model: the round-1 model (its normalisation is kept).
        noisy_images: ``(H, W, 3)`` float32 [0, 1], the selected noisy views.
        renders: the detail targets (round-1 renders) of the same views, same sizes.
        config: loss weights and schedule.
        seed: seeds patches and masks.

    Raises:
        InputError: counts or sizes differ, or an image is unusable.
    """
    cfg = config or Round2Config()
    noisy_t, render_t = _check_views(noisy_images, renders, device=_model_device(model))
    return _finetune(model, noisy_t, render_t, cfg, seed=seed)


def _finetune(model: N2VModel, noisy_t: list[Tensor], render_t: list[Tensor], cfg: Round2Config, *,
              seed: int) -> N2VModel:
    rng = np.random.default_rng(seed)
    gen = torch.Generator(device=noisy_t[0].device).manual_seed(seed)
    patch = effective_patch_px(noisy_t, cfg.patch_px)
    unet = model.unet
    unet.train()
    replicas = weight_sharing_replicas(unet, cfg.batch_chunks, batch_size=cfg.batch_size)
    opt = torch.optim.Adam(unet.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: lr_factor(s, steps=cfg.steps, warmup_frac=0.0, min_lr_frac=0.05))

    def loss(net: torch.nn.Module, inp: Tensor, noisy: Tensor, render: Tensor) -> Tensor:
        return joint_loss(model.apply(inp, unet=net), noisy, render, cfg).total

    with one_thread_per_task(), progress_bar(desc="round2", total=cfg.steps) as bar:
        for _ in range(cfg.steps):
            noisy, render = sample_patches(noisy_t, patch_px=patch, batch_size=cfg.batch_size, rng=rng,
                                           paired=render_t)
            inp = noisy
            if cfg.mask_input:
                inp = mask_pixels(noisy, p=model.mask_prob, replacement=model.replacement, radius=model.radius,
                                  generator=gen).masked
            value = chunked_backward(replicas, StepBatch((inp, noisy, render), loss))
            opt.step()
            sched.step()
            model.history.append(value)
            bar.update(1)
    unet.eval()
    model.blind_spot = False  # trained on the full input now: no centre-pixel fusion at inference
    return model


@dataclass(frozen=True)
class TrustTarget:
    """Output of `render_trust_target` (``[B, 3, H, W]`` tensors).

    Attributes:
        target: the detail target ``w * render + (1 - w) * round1``.
        render_weight: ``w`` in ``[0, 1]``.
        round1: the round-1 estimate (blind-spot prediction fused with the observation).
    """

    target: Tensor
    render_weight: Tensor
    round1: Tensor


def render_trust_target(noisy: Tensor, prior_mean: Tensor, render: Tensor, *, noise_sigma: float | Tensor,
                        window_sigma_px: float = 2.0) -> TrustTarget:
    """Per-pixel inverse-variance blend of the round-1 render and the round-1 denoised estimate.

    With the noisy photo ``y = x + n`` (``n`` white, std ``s``), the round-1
    blind-spot prediction ``mu`` (independent of ``n`` at each pixel) and the
    render ``r``, local second moments over a Gaussian window ``G`` estimate
    squared errors without the clean image ``x``:

    - render: ``e_r = max(G (y - r)^2 - s^2, 0)`` (``E (y - r)^2 = s^2 + (x - r)^2``
      when the render does not copy this view's noise);
    - round 1: ``mu``'s error ``v = max(G (y - mu)^2 - s^2, 0)``; the round-1 output
      ``r1 = mu + v / (v + s^2) (y - mu)`` (`denoise.fusion`) has posterior variance
      ``e_1 = v s^2 / (v + s^2)``.

    Both estimates carry sampling error: a variance estimated from a window of
    ``n_eff = 4 pi sigma_w^2`` independent pixels has relative std ``sqrt(2 / n_eff)``,
    so ``f = s^2 sqrt(2 / n_eff)`` is added to each as a floor. The weight of the
    render is ``w = (e_1 + f) / (e_1 + e_r + 2 f)``: where the render is as good as
    round 1 (or better) it contributes at least half, where it is off by more than
    the noise explains, round 1 keeps the pixel (the self-consistency guard: round 2
    cannot move away from round 1 where the scene gives no evidence).

    Args:
        noisy: ``[B, 3, H, W]`` photos ``y``.
        prior_mean: ``[B, 3, H, W]`` round-1 blind-spot prediction ``mu`` (not fused).
        render: ``[B, 3, H, W]`` round-1 renders.
        noise_sigma: ``s``, a float or a tensor broadcastable to ``[B, 1, 1, 1]``.
        window_sigma_px: ``sigma_w``, the window of the local statistics (that of `denoise.fusion`).

    Returns:
        `TrustTarget`.
    """
    if not window_sigma_px > 0:
        raise ValueError(f"window_sigma_px must be > 0, got {window_sigma_px}")
    v_noise = torch.as_tensor(noise_sigma, dtype=noisy.dtype, device=noisy.device) ** 2
    r1 = fuse_with_observation(prior_mean, noisy, noise_sigma=noise_sigma, window_sigma_px=window_sigma_px)
    v_mu = (gaussian_blur((noisy - prior_mean) ** 2, sigma=window_sigma_px) - v_noise).clamp_min(0.0)
    err_round1 = v_mu * v_noise / (v_mu + v_noise).clamp_min(torch.finfo(noisy.dtype).tiny)
    err_render = (gaussian_blur((noisy - render) ** 2, sigma=window_sigma_px) - v_noise).clamp_min(0.0)
    floor = v_noise * float(np.sqrt(2.0 / (4.0 * np.pi * window_sigma_px**2)))
    den = err_round1 + err_render + 2.0 * floor
    w = torch.where(den > 0, (err_round1 + floor) / den.clamp_min(torch.finfo(noisy.dtype).tiny),
                    torch.full_like(den, 0.5))
    return TrustTarget(target=w * render + (1.0 - w) * r1, render_weight=w, round1=r1)
