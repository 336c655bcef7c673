"""Noise2Void training of the UNet (Krull et al. 2019), with the N2V2 options.

Training follows the paper: random patches from all views; each pixel masked
independently with probability ``p`` (``mask_prob``, 0.04 here, chosen by measurement;
N2V's reference code masks about 0.2 % of a patch) and its value replaced (see
`denoise.masking`); ``out = masked + alpha * UNet(masked)`` with
``alpha = 0.5`` (normalised units, `denoise.model`); mean-squared error against
the *unmasked* noisy value on the masked pixels only. Adam with a linear
warm-up and a cosine decay of the learning rate. Everything is seeded.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch

from denoise.images import images_to_tensors
from denoise.masking import REPLACEMENTS, Replacement, mask_pixels
from denoise.model import N2VModel
from denoise.parallel import in_parallel, one_thread_per_task, run_tasks
from denoise.patches import effective_patch_px, sample_patches
from denoise.training_restart import TrainingRestart
from denoise.unet import UNet, UNetConfig
from mvgeo.common.errors import ConfigError, DgsError
from mvgeo.common.progress import progress_bar

_log = logging.getLogger(__name__)

#: Self-supervised training methods on the same UNet (`N2VConfig.method`): ``"n2v"`` here;
#: ``"neighbor2neighbor"`` (`denoise.neighbor2neighbor`) and ``"r2r"`` (`denoise.r2r`) train a
#: non-blind network. `denoise.self_supervised.train_with_method` / `denoise_with_method` train and
#: apply any of them.
Method = Literal["n2v", "neighbor2neighbor", "r2r"]
METHODS: tuple[str, ...] = ("n2v", "neighbor2neighbor", "r2r")


@dataclass(frozen=True)
class N2VConfig:
    """Round-1 (Noise2Void) training options. Defaults are the CPU preset ``"default"``.

    Defaults were measured on data_synth ``object_ring`` views (256x192, sigma 25/255; not
    the benchmark's scene), torch single-threaded on the shared 2-core machine:

    - ``lr``: 2e-3 (the previous default) is at the edge of stability: with 600 steps it
      diverged (loss ~70 in normalised units, output 5 dB; a supervised run of the same
      UNet at 2e-3 and 600 steps diverged too), with 400 steps it did not. 4e-4 (N2V's)
      is stable but slower: 22.18 dB blind-spot output after 400 steps; 1e-3 reached
      22.28 dB with a lower loss. Hence 1e-3.
    - ``mask_prob`` 0.15 instead of 0.04 (more loss pixels per step) was worse: 21.48 vs
      22.18 dB at 400 steps.
    - the centre-cancelling init (`init_centre_cancelling`, ``UNetConfig.input_skip``)
      matters at CPU step counts: the plain N2V formulation reached 19.23 dB (below the
      noisy input, 20.34) after the same 400 steps at 4e-4.
    - the blind-spot output then gains ~2 dB from fusion with the centre pixel at
      inference (`denoise.fusion`): 22.28 -> 24.31 dB; NLM (best h) 23.24, TV 23.57.
    - the ``n2v2`` preset (blur-pool, no top skip, median replacement) at 400 steps: 21.80 dB
      blind-spot, 23.98 fused (vs 22.28 / 24.31): no checkerboard gain to pay for at this budget.
    - ``replacement="uniform_withCP"`` (a value from the 11x11 window, N2V's reference code)
      instead of ``permute`` (from anywhere in the patch, the issue's reading of the paper):
      blind-spot output 22.89 vs 22.21 dB, fused (PCA noise estimate) 24.69 dB vs 24.48 dB for
      permute fused with the *true* sigma (400 steps). Not yet the default: measured after the
      benchmark run had started; a candidate. 800 steps (permute): 22.54 / 24.70 dB at twice
      the training time.
    - width 8 (the ``fast`` preset) costs ~0.2 dB (24.13 dB fused) for 49 s of training
      against 111 s at width 16 (400 steps each; separate runs, load 2-5: a rough ratio);
      800 steps at width 8 gave 24.35 dB: the curve flattens after ~400 steps.

    Attributes:
        unet: network architecture (width 16, 4 levels).
        steps: optimiser steps (each one batch).
        batch_size: patches per step.
        patch_px: patch side in pixels (smaller images use their smallest side).
        lr: peak Adam learning rate.
        warmup_frac: fraction of `steps` with a linear learning-rate warm-up.
        min_lr_frac: the cosine decay ends at ``lr * min_lr_frac``.
        mask_prob: probability that a pixel is masked (0.04; N2V's reference code: about 0.002).
        replacement: ``"permute"`` (N2V paper), ``"uniform_withCP"`` or ``"median"`` (N2V2).
        radius: window radius for ``uniform_withCP`` / ``median`` (N2V: 5).
        alpha: residual scale in ``out = masked + alpha * UNet(masked)``.
        augment: random rot90/flip of patches.
        method: training objective (`METHODS`); the fields above that name the N2V masking
            apply to ``"n2v"`` only.
        nb2nb_gamma: Neighbor2Neighbor regulariser weight at the last step (it ramps up
            linearly from 0, as in the paper's code; paper: 2).
        r2r_alpha: Recorrupted-to-Recorrupted scale: input ``y + alpha z``, target ``y - z / alpha``
            (paper: 0.5).
        batch_chunks: a training step's batch is split into this many chunks of consecutive samples, each
            run through the network with one torch thread, on up to as many Python threads as the caller's
            torch thread count (`denoise.parallel`), their gradients summed in chunk order. The trained
            weights depend on this count, not on the machine's or the Ray task's CPUs (a whole batch on 2
            intra-op threads differs from 1 thread by 3.6e-3 in the weights after 60 steps: oneDNN sums a
            convolution's weight gradient in per-thread chunks). On CPU only; other devices take the
            batch whole. 2: on the 2-core reference machine as fast as the whole batch on 2 intra-op
            threads (width 16: 0.85 s against 0.79-1.07 s for 20 steps), and 1.05x the whole batch's time on
            one thread. A batch of fewer samples has one chunk per sample. Each chunk's loss is its own
            mean (for the masked objectives, over its own masked pixels), weighted by its share of the
            samples.
        divergence_guard: watch the training loss (`DivergenceGuard`: a window of 50 steps whose median
            loss is more than 3x the lowest window median so far, or a non-finite loss) and start a
            diverging run again at half the learning rate (`optimise_unet`). Runs that do not diverge are
            unchanged to the bit. Measured: one of 21 GPU trainings of R2R at width 32 or more on the DTU
            photos ended at 6.4 dB instead of 31 dB (the same seed repeated three times: 31.06-31.10 dB;
            docs/bench/denoise_real.md).
    """

    unet: UNetConfig = field(default_factory=UNetConfig)
    steps: int = 400
    batch_size: int = 8
    patch_px: int = 64
    lr: float = 1e-3
    warmup_frac: float = 0.05
    min_lr_frac: float = 0.02
    mask_prob: float = 0.04
    replacement: Replacement = "permute"
    radius: int = 5
    alpha: float = 0.5
    augment: bool = True
    method: Method = "n2v"
    nb2nb_gamma: float = 2.0
    r2r_alpha: float = 0.5
    batch_chunks: int = 2
    divergence_guard: bool = True

    def __post_init__(self) -> None:
        positive = ("steps", "batch_size", "patch_px", "radius")
        for key in positive:
            if getattr(self, key) < 1:
                raise ConfigError(f"must be >= 1, got {getattr(self, key)}", key=key)
        if self.batch_chunks < 1:
            raise ConfigError(f"must be >= 1, got {self.batch_chunks}", key="batch_chunks")
        if not self.lr > 0:
            raise ConfigError(f"must be > 0, got {self.lr}", key="lr")
        if not 0 < self.mask_prob < 1:
            raise ConfigError(f"must be in (0, 1), got {self.mask_prob}", key="mask_prob")
        if not 0 <= self.warmup_frac < 1 or not 0 <= self.min_lr_frac <= 1:
            raise ConfigError("warmup_frac must be in [0, 1) and min_lr_frac in [0, 1]", key="warmup_frac")
        if self.replacement not in REPLACEMENTS:
            raise ConfigError(f"unknown replacement {self.replacement!r}", key="replacement",
                              expected=" or ".join(REPLACEMENTS))
        if self.method not in METHODS:
            raise ConfigError(f"unknown method {self.method!r}", key="method", expected=" or ".join(METHODS))
        if not self.nb2nb_gamma >= 0:
            raise ConfigError(f"must be >= 0, got {self.nb2nb_gamma}", key="nb2nb_gamma")
        if not self.r2r_alpha > 0:
            raise ConfigError(f"must be > 0, got {self.r2r_alpha}", key="r2r_alpha")


#: Named presets. ``fast``: the demo (about a minute of training on one core, width 8);
#: ``default``: about two minutes on one core (width 16); ``wide``: the default at width 32, 2.3-2.6x its
#: CPU time per training step: on the whole real photos at 2000 R2R steps +0.25-0.6 dB and +0.007-0.019
#: SSIM (DTU scan24, sigma 25 and Poisson-Gaussian; docs/bench/denoise_real.md, "the network's size"); ``n2v2``:
#: the default with the N2V2 anti-checkerboard options. Measurements: see `N2VConfig`.
N2V_PRESETS: dict[str, N2VConfig] = {
    "fast": N2VConfig(unet=UNetConfig(width=8)),
    "default": N2VConfig(),
    "wide": N2VConfig(unet=UNetConfig(width=32)),
    "n2v2": N2VConfig(unet=UNetConfig(blurpool=True, top_skip=False), replacement="median"),
}


def n2v_preset(name: str, **overrides) -> N2VConfig:
    """A preset by name, with field overrides (e.g. ``steps=200``)."""
    if name not in N2V_PRESETS:
        raise ConfigError(f"unknown preset {name!r}", key="preset", expected=" or ".join(N2V_PRESETS))
    return replace(N2V_PRESETS[name], **overrides)


def lr_factor(step: int, *, steps: int, warmup_frac: float, min_lr_frac: float) -> float:
    """Learning-rate multiplier at `step` (0-based): linear warm-up, then cosine to `min_lr_frac`."""
    warm = int(round(warmup_frac * steps))
    if step < warm:
        return (step + 1) / warm
    t = (step - warm) / max(1, steps - warm)
    return min_lr_frac + (1 - min_lr_frac) * 0.5 * (1 + math.cos(math.pi * min(t, 1.0)))


def channel_stats(tensors: Sequence[torch.Tensor]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Per-channel mean and standard deviation over all pixels (std floored at `N2VModel.STD_FLOOR`)."""
    flat = torch.cat([t.reshape(t.shape[0], -1).double() for t in tensors], dim=1)
    mean = flat.mean(1)
    std = flat.std(1, correction=0).clamp_min(N2VModel.STD_FLOOR)
    return tuple(float(v) for v in mean), tuple(float(v) for v in std)


def masked_mse(out: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over masked pixels and all channels (0 if nothing is masked).

    Args:
        out, target: ``[B, C, H, W]``.
        mask: ``[B, 1, H, W]`` bool.
    """
    m = mask.to(out.dtype)
    denom = (m.sum() * out.shape[1]).clamp_min(1.0)
    return (((out - target) ** 2) * m).sum() / denom


def init_centre_cancelling(unet: UNet, alpha: float) -> None:
    """Initialise the head's linear input path to ``-1 / alpha`` times the identity.

    Then ``x + alpha * UNet(x)`` starts as ``alpha * (features part)``: the
    prediction ignores the centre pixel from step 0, which is what the N2V loss
    drives it to (a masked pixel's own value is a random replacement). Without
    this, Adam needs ~``2 / lr`` steps just to grow that weight to -2; with it,
    training on CPU converges in a few hundred steps. Needs ``input_skip``.
    """
    if not unet.config.input_skip:
        return
    c_in = unet.config.in_channels
    with torch.no_grad():
        w = unet.head.weight  # (C_out, C_feat + C_in, 1, 1)
        w[:, -c_in:] = 0.0
        for c in range(min(c_in, unet.config.out_channels)):
            w[c, w.shape[1] - c_in + c] = -1.0 / alpha


def new_model(config: N2VConfig, tensors: Sequence[torch.Tensor], *, seed: int) -> N2VModel:
    """A freshly initialised model (weights from `seed`, global RNG state left untouched)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        unet = UNet(config.unet)
    init_centre_cancelling(unet, config.alpha)
    mean, std = channel_stats(tensors)
    return N2VModel(unet=unet, mean=mean, std=std, alpha=config.alpha, mask_prob=config.mask_prob,
                    replacement=config.replacement, radius=config.radius)


def train_n2v(images: Sequence[np.ndarray], config: N2VConfig | None = None, *, seed: int = 0,
              model: N2VModel | None = None, device: str | torch.device = "cpu") -> N2VModel:
    """Train a UNet with Noise2Void on the noisy `images` themselves.

    Args:
        images: ``(H, W, 3)`` float32 RGB in ``[0, 1]`` (``(H, W)`` grayscale accepted); sizes may differ.
        config: training options (default: the ``default`` preset).
        seed: seeds the weights, the patches and the masks.
        model: continue training this model instead of a new one (its normalisation is kept).
        device: torch device of the training (the model is moved there and returned there;
            patches are cut on it). On CPU the result does not depend on this argument.

    Returns:
        The trained `N2VModel` (in eval mode, on `device`), with the per-step losses in ``history``.

    Raises:
        InputError: empty list, non-finite values, images below 2x2 px.
    """
    config = config or N2VConfig()
    if config.method != "n2v":
        raise ConfigError(f"train_n2v trains method 'n2v', got {config.method!r}", key="method",
                          expected="denoise.self_supervised.train_with_method for every method")
    tensors = images_to_tensors(images)
    device = torch.device(device)
    rng = np.random.default_rng(seed)
    gen = torch.Generator(device=device).manual_seed(seed)
    model = model or new_model(config, tensors, seed=seed)
    model.unet.to(device)
    patch = effective_patch_px(tensors, config.patch_px)
    if patch < config.patch_px:
        _log.warning("images are smaller than the %d px patch; training on %d px patches", config.patch_px, patch)
    # Normalise once; the network's residual lives in normalised units (see N2VModel.apply).
    mean = torch.tensor(model.mean).reshape(3, 1, 1)
    std = torch.tensor(model.std).reshape(3, 1, 1)
    normed = [((t - mean) / std).to(device) for t in tensors]
    def blind_spot_loss(unet: torch.nn.Module, batch: torch.Tensor, masked: torch.Tensor,
                        mask: torch.Tensor) -> torch.Tensor:
        return masked_mse(masked + model.alpha * unet(masked), batch, mask)

    def blind_spot_batch(step: int) -> StepBatch:
        batch, _ = sample_patches(normed, patch_px=patch, batch_size=config.batch_size, rng=rng,
                                  augment=config.augment)
        mb = mask_pixels(batch, p=config.mask_prob, replacement=config.replacement, radius=config.radius,
                         generator=gen)
        return StepBatch((batch, mb.masked, mb.mask), blind_spot_loss)

    return optimise_unet(model, config, blind_spot_batch, desc="n2v")


class TrainingDivergedError(DgsError):
    """The denoiser's training diverged at every learning rate tried (`optimise_unet`)."""


class DivergenceGuard:
    """Tells a diverging training run (`N2VConfig.divergence_guard`, `optimise_unet`).

    The losses are taken in windows of `window` steps. A window whose median is more than `factor` times
    the lowest positive window median so far, or a non-finite loss, is a divergence. The median of a
    window, not one step's loss, so that one hard batch is none (`finish` judges a short last stretch of
    steps together with the window before it). `factor` 3 leaves room for Neighbor2Neighbor, whose loss rises
    by design as its regulariser's weight ramps up (1.25-1.5x the lowest at the default weight 2).
    """

    def __init__(self, *, window: int = 50, factor: float = 3.0):
        self.window, self.factor = window, factor
        self.best = math.inf
        self.losses: list[float] = []
        self.last: list[float] = []

    def check(self, loss: float) -> bool:
        """Record one step's loss; True at a divergence."""
        self.losses.append(loss)
        if math.isfinite(loss) and len(self.losses) < self.window:
            return False
        window, self.losses = self.losses, []
        self.last = window
        return self._diverged(window)

    def finish(self) -> bool:
        """Judge the steps after the last full window: alone when they are at least half a window, else
        with that window (so that one hard last batch is no divergence); True at a divergence."""
        tail, self.losses = self.losses, []
        if not tail:
            return False
        return self._diverged(tail if 2 * len(tail) >= self.window else self.last + tail)

    def _diverged(self, losses: list[float]) -> bool:
        if not all(map(math.isfinite, losses)):
            return True
        median = float(np.median(losses))
        if median > self.factor * self.best:
            return True
        if median > 0:  # a zero median (no loss pixels) sets no scale
            self.best = min(self.best, median)
        return False


@dataclass(frozen=True)
class StepBatch:
    """One training step's batch, as `optimise_unet` splits it.

    Attributes:
        rows: tensors whose first dimension is the sample (patches, masks, targets, drawn for the whole
            batch, so that the random draws do not depend on the split).
        loss: ``loss(unet, *rows_of_a_chunk)``: the objective's mean over those samples, computed with
            `unet` (the model's network or a replica sharing its weights).
    """

    rows: tuple[torch.Tensor, ...]
    loss: Callable[..., torch.Tensor]


def chunk_bounds(n: int, chunks: int) -> list[tuple[int, int]]:
    """``min(chunks, n)`` consecutive ``(start, stop)`` ranges covering ``range(n)``, sizes differing by at
    most one (the first ones larger)."""
    k = max(1, min(chunks, n))
    sizes = [n // k + (1 if i < n % k else 0) for i in range(k)]
    starts = np.cumsum([0, *sizes])
    return [(int(a), int(b)) for a, b in zip(starts[:-1], starts[1:], strict=True)]


def weight_sharing_replicas(unet: torch.nn.Module, chunks: int, *, batch_size: int) -> list[torch.nn.Module]:
    """`unet` and copies whose parameters share its storage (an optimiser step on `unet` moves them too) but
    keep their own gradients: one network per chunk of a `batch_size` batch split into `chunks` on CPU
    (`chunk_bounds`), `unet` alone on other devices, which take the batch whole."""
    count = min(chunks, batch_size) if in_parallel(next(unet.parameters()).device) else 1
    replicas = [unet]
    for _ in range(count - 1):
        twin = copy.deepcopy(unet)
        for p_twin, p in zip(twin.parameters(), unet.parameters(), strict=True):
            p_twin.data = p.data
        replicas.append(twin)
    return replicas


def chunked_backward(replicas: Sequence[torch.nn.Module], batch: StepBatch) -> float:
    """Backward pass of `batch`'s loss split into ``len(replicas)`` chunks (`chunk_bounds`), chunk k through
    ``replicas[k]`` (`weight_sharing_replicas`), the chunks on `denoise.parallel.run_tasks`; the gradients
    end summed in chunk order in ``replicas[0]``'s parameters. Returns the step's loss: the chunks' means
    weighted by their share of the samples, summed in chunk order (may be non-finite)."""
    n = int(batch.rows[0].shape[0])
    bounds = chunk_bounds(n, len(replicas))

    def one(k: int) -> float:
        a, b = bounds[k]
        net = replicas[k]
        net.zero_grad(set_to_none=True)
        loss = batch.loss(net, *(t[a:b] for t in batch.rows)) * ((b - a) / n)
        loss.backward()
        return loss.item()

    values = run_tasks(one, range(len(bounds)), device=next(replicas[0].parameters()).device)
    for k in range(1, len(bounds)):
        for p, p_k in zip(replicas[0].parameters(), replicas[k].parameters(), strict=True):
            if p_k.grad is None:
                continue
            if p.grad is None:
                p.grad = p_k.grad.clone()
            else:
                p.grad.add_(p_k.grad)
    return float(sum(values))


#: Restarts at a halved learning rate after a divergence (`optimise_unet`): 4 reach 1/16 of it.
MAX_RESTARTS = 4


def optimise_unet(model: N2VModel, config: N2VConfig, batch_at_step: Callable[[int], StepBatch], *,
                  desc: str) -> N2VModel:
    """The training loop every self-supervised objective shares: Adam at `config.lr` with the warm-up
    and cosine schedule of `lr_factor`, `config.steps` steps, `batch_at_step(step)` drawing each step's
    batch and giving its loss (`StepBatch`), split into `config.batch_chunks` chunks on CPU
    (`chunked_backward`), the (finite) losses appended to `model.history`. Returns `model` in eval mode.

    With `config.divergence_guard`, a run the `DivergenceGuard` finds diverging starts again from the
    weights it started from, at half the learning rate and with a new optimiser (the batches continue
    from where they were), up to `MAX_RESTARTS` times; `model.history` then holds the last run's losses and
    `model.restarts` the step and learning rate of each abandoned run.
    A run that does not diverge is unchanged to the bit.

    Raises:
        TrainingDivergedError: the last restart diverged too.
    """
    unet = model.unet
    start = {k: v.detach().clone() for k, v in unet.state_dict().items()} if config.divergence_guard else None
    n_history = len(model.history)
    lr = config.lr
    for attempt in range(MAX_RESTARTS + 1):
        at = _train(model, config, batch_at_step, desc=desc, lr=lr)
        if at is None:
            break
        if attempt == MAX_RESTARTS:
            raise TrainingDivergedError(
                f"the {desc} training diverged at step {at} even at learning rate {lr:.3g} ({config.lr:.3g} "
                f"halved {MAX_RESTARTS} times): check the images (near-constant photos, or a noise level far "
                "from the one the objective assumes); from Python, a lower N2VConfig.lr")
        _log.warning("the %s training diverged at step %d (learning rate %.3g): starting again at %.3g",
                     desc, at, lr, lr * 0.5)
        unet.load_state_dict(start)
        del model.history[n_history:]
        model.restarts.append(TrainingRestart(step=int(at), lr=float(lr)))
        lr *= 0.5
    unet.eval()
    return model


def _train(model: N2VModel, config: N2VConfig, batch_at_step: Callable[[int], StepBatch], *, desc: str,
           lr: float) -> int | None:
    """One run of `optimise_unet`'s loop at peak learning rate `lr`; the step it diverged at, or None."""
    unet = model.unet
    unet.train()
    replicas = weight_sharing_replicas(unet, config.batch_chunks, batch_size=config.batch_size)
    opt = torch.optim.Adam(unet.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: lr_factor(s, steps=config.steps, warmup_frac=config.warmup_frac,
                                 min_lr_frac=config.min_lr_frac))
    guard = DivergenceGuard() if config.divergence_guard else None
    skipped = 0
    with one_thread_per_task(), progress_bar(desc=desc, total=config.steps) as bar:
        for step in range(config.steps):
            value = chunked_backward(replicas, batch_at_step(step))
            if math.isfinite(value):  # a non-finite loss would write NaNs into the weights: step skipped
                opt.step()
                model.history.append(value)
            else:
                skipped += 1
            sched.step()
            bar.update(1)
            bar.set_postfix(loss=f"{value:.4f}")
            if guard is not None and guard.check(value):
                return step
    if skipped:
        _log.warning("the %s training skipped %d of %d steps whose loss was not finite", desc, skipped, config.steps)
    return config.steps - 1 if guard is not None and guard.finish() else None
