"""Applying a trained `N2VModel`: masked-mean or single-pass prediction, tiled.

N2V predicts in one pass on the unmasked image (``passes=0``); averaging the
prediction over K random maskings (``passes=K``) is this package's option: a
blind-spot estimate of every pixel, averaged to reduce its variance.
Large images are processed in tiles: each tile's *core* is predicted from the
core plus `margin_px` of context on every side and only the core is kept, so
tiles never blend. The result is not bit-exact against a whole-image pass (the
UNet's receptive field exceeds the margin, and its max-pooling grid sits
differently in each tile), but the difference is small and shows no seam at
the tiles' borders (a trained `fast` model on a 700 x 650 photo in 512-px
tiles: 0.21/255 on average, 8.3/255 at most, at the image's edge; the jump
across a border 0.054/255 against 0.041 elsewhere; tests/denoise/
test_inference.py bounds a small model's under one 8-bit step). The default core, `TILE_PX` = 512,
runs images up to 608 px on a side in one piece: at 504x378 a whole-image pass takes 0.22 s on
2 cores against 0.40 s in 256-px tiles, whose overlapping margins recompute half the image.

Measured on data_synth ``object_ring`` clean views + noise (8 views at 192x144,
default preset; not the benchmark's scene): sigma 25/255, fused output K=8 24.20 dB,
K=0 24.23 dB at a seventh of the time (the centre-cancelling start makes the
unmasked pass as good), dihedral self-ensemble 24.23 dB (no gain worth a default);
fusion window 1 / 2 / 3 px: 24.05 / 24.20 / 24.20 dB; fusion with the true sigma
24.48 dB vs 24.20 dB with the Laplacian (`estimate_noise_sigma_robust`) estimate,
which texture grain inflates to 27.9/255: hence the PCA estimate (24.6/255 there).
Poisson-Gaussian (a = 0.01, s = 5/255): constant-std fusion 25.94 dB, per-intensity
curve 26.22 dB (true curve 26.23 dB; best NLM h 26.24 dB): hence ``noise_model="auto"``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from denoise.fusion import fuse_with_observation
from denoise.images import image_to_tensor, tensor_to_image
from denoise.masking import mask_pixels
from denoise.model import N2VModel
from denoise.noise_level import (
    NoiseCurve,
    constant_noise_sigma_luma,
    estimate_noise_curve,
    estimate_noise_sigma,
    estimate_noise_sigma_pca,
)
from denoise.parallel import group_size, one_thread_per_task, run_tasks
from mvgeo.common.errors import check_shape
from mvgeo.common.progress import progress

_log = logging.getLogger(__name__)

#: Default side of a tile's kept core, and the context added around it (`predict_tiled`).
TILE_PX = 512
MARGIN_PX = 48

#: Images whose estimated noise std (`estimate_noise_sigma`) is below this are returned
#: unchanged: N2V predicts each pixel from its neighbours, which on a noise-free image
#: can only lose detail (measured 23 dB vs the input on a clean synthetic scene).
CLEAN_SIGMA = 1.0 / 255

NoiseModel = Literal["auto", "constant", "curve", "luma"]
NOISE_MODELS: tuple[str, ...] = ("auto", "constant", "curve", "luma")


def fusion_noise_sigma(img: np.ndarray, prior_mean: Tensor, *, noise_model: NoiseModel = "auto") -> float | Tensor:
    """The noise std that `fuse_with_observation` uses for one image.

    Args:
        img: the noisy image (numpy, as given to `denoise_images`).
        prior_mean: ``[1, 3, H, W]`` blind-spot prediction (where a curve is evaluated).
        noise_model: ``"constant"``: one std (`estimate_noise_sigma_pca` of the unclipped patches:
            over all patches, clipping at 0 / 1 reads the noise low, 22/255 for a true 25/255 on
            the DTU photos, about 10/255 on the temple's black background); ``"curve"``: a
            per-pixel std from the image's `NoiseCurve` at `prior_mean`; ``"auto"``: the curve
            when its signal-dependent term dominates at the image's median intensity
            (``gain * median > floor``, e.g. shot noise), else the constant; ``"luma"``: one std read on the
            luma (`denoise.noise_level.constant_noise_sigma_luma`), for photos whose noise is
            chroma-subsampled (a JPEG's; `denoise.pixel_shuffle.choose_stride` decides it for a set).

    Returns:
        A float, or a ``[1, 3, H, W]`` tensor.
    """
    if noise_model == "luma":
        return constant_noise_sigma_luma(img)
    curve = signal_dependent_curve(img, noise_model)
    return estimate_noise_sigma_pca(img, exclude_clipped=True) if curve is None else curve.sigma_at(prior_mean)


def signal_dependent_curve(img: np.ndarray, noise_model: NoiseModel) -> NoiseCurve | None:
    """The image's `NoiseCurve` where `noise_model` asks for one, else None (use one std): always for
    ``"curve"``, never for ``"constant"`` or ``"luma"``; for ``"auto"`` where the curve's signal-dependent term
    dominates at the image's median intensity (``gain * median > floor``, e.g. shot noise).

    Raises:
        ValueError: unknown `noise_model`.
    """
    if noise_model not in NOISE_MODELS:
        raise ValueError(f"noise_model must be one of {NOISE_MODELS}, got {noise_model!r}")
    if noise_model in ("constant", "luma"):
        return None
    curve = estimate_noise_curve(img)
    return curve if noise_model == "curve" or curve.gain * float(np.median(img)) > curve.floor else None


def tile_starts(n: int, core: int) -> list[int]:
    """Start offsets of cores of size `core` covering ``0..n`` (the last one shifted to end at `n`)."""
    if n <= core:
        return [0]
    starts = list(range(0, n - core, core))
    starts.append(n - core)
    return starts


@torch.no_grad()
def predict_tiled(model: N2VModel, x: Tensor, *, tile_px: int = TILE_PX, margin_px: int = MARGIN_PX) -> Tensor:
    """One network pass over an image batch in overlapping tiles.

    Args:
        x: ``[B, 3, H, W]`` in ``[0, 1]`` units (already masked if wanted).
        tile_px: side of the kept core of each tile; images that fit in one
            core plus margins are processed whole.
        margin_px: context added on every side of a core (clipped at the image border).

    Returns:
        ``[B, 3, H, W]``, unclipped.
    """
    check_shape(x, ["B", "C", "H", "W"], "x")
    if tile_px < 1 or margin_px < 0:
        raise ValueError("tile_px must be >= 1 and margin_px >= 0")
    h, w = x.shape[-2:]
    if h <= tile_px + 2 * margin_px and w <= tile_px + 2 * margin_px:
        return model.apply(x)
    cores = [(y0, min(y0 + tile_px, h), x0, min(x0 + tile_px, w))
             for y0 in tile_starts(h, tile_px) for x0 in tile_starts(w, tile_px)]

    def core(c: tuple[int, int, int, int]) -> Tensor:
        y0, y1, x0, x1 = c
        cy0, cx0 = max(0, y0 - margin_px), max(0, x0 - margin_px)
        cy1, cx1 = min(h, y1 + margin_px), min(w, x1 + margin_px)
        return model.apply(x[..., cy0:cy1, cx0:cx1])[..., y0 - cy0 : y1 - cy0, x0 - cx0 : x1 - cx0]

    # The tiles are fixed by `tile_px` and run one per task (`denoise.parallel`: one torch thread each, on
    # the caller's thread budget; in order inside a task that is itself one of several): the same bits
    # whatever the threads.
    out = torch.empty_like(x)
    for (y0, y1, x0, x1), pred in zip(cores, run_tasks(core, cores, device=x.device), strict=True):
        out[..., y0:y1, x0:x1] = pred
    return out


def dihedral(x: Tensor, k: int, *, inverse: bool = False) -> Tensor:
    """The `k`-th of the 8 rotations/reflections of the square (``k % 8``) on the last two dims.

    ``k % 4`` quarter turns (``torch.rot90``), preceded by a horizontal flip when
    ``k % 8 >= 4``; ``inverse=True`` undoes it.
    """
    k %= 8
    if not inverse:
        x = torch.flip(x, dims=(-1,)) if k >= 4 else x
        return torch.rot90(x, k % 4, dims=(-2, -1))
    x = torch.rot90(x, -(k % 4), dims=(-2, -1))
    return torch.flip(x, dims=(-1,)) if k >= 4 else x


@torch.no_grad()
def denoise_tensor(model: N2VModel, x: Tensor, *, passes: int = 8, generator: torch.Generator | None = None,
                   tile_px: int = TILE_PX, margin_px: int = MARGIN_PX, dihedral_ensemble: bool = False) -> Tensor:
    """Denoise one ``[1, 3, H, W]`` batch: mean over `passes` random maskings, or one unmasked pass if 0.

    Masks use the model's training masking (`N2VModel.mask_prob`, ``replacement``,
    ``radius``) over the whole image (not per tile), so tiling does not change
    which values are swapped in. With `dihedral_ensemble`, pass ``k`` runs on the
    ``k``-th rotation/reflection of the image (`dihedral`) and is transformed back
    (a self-ensemble; training sees the same 8 transforms as augmentation).
    """
    if passes < 0:
        raise ValueError(f"passes must be >= 0, got {passes}")
    model.unet.eval()
    if passes == 0:
        with one_thread_per_task():
            return predict_tiled(model, x, tile_px=tile_px, margin_px=margin_px)

    def draw(k: int) -> Tensor:
        xt = dihedral(x, k) if dihedral_ensemble else x
        return mask_pixels(xt, p=model.mask_prob, replacement=model.replacement, radius=model.radius,
                           generator=generator).masked

    def predict(k: int, masked: Tensor) -> Tensor:
        pred = predict_tiled(model, masked, tile_px=tile_px, margin_px=margin_px)
        return dihedral(pred, k, inverse=True) if dihedral_ensemble else pred

    return mean_of_passes(x, passes, draw, predict)


def mean_of_passes(x: Tensor, passes: int, draw: Callable[[int], Tensor],
                   predict: Callable[[int, Tensor], Tensor]) -> Tensor:
    """``mean_k predict(k, draw(k))`` over ``k < passes``: the inputs drawn here in pass order (`draw` may use
    a shared random generator), the predictions run `denoise.parallel.group_size` at a time on
    `denoise.parallel.run_tasks` and summed in pass order, so the result does not depend on the threads."""
    if passes < 1:
        raise ValueError(f"passes must be >= 1, got {passes}")
    acc = torch.zeros_like(x)
    with one_thread_per_task():
        step = group_size(x)
        for start in range(0, passes, step):
            group = [(k, draw(k)) for k in range(start, min(passes, start + step))]
            for pred in run_tasks(lambda kx: predict(*kx), group, device=x.device):
                acc += pred
    return acc / passes


def denoise_images(model: N2VModel, images: Sequence[np.ndarray], *, passes: int = 8, seed: int = 0,
                   tile_px: int = TILE_PX, margin_px: int = MARGIN_PX, clean_sigma: float = CLEAN_SIGMA,
                   fuse: bool | None = None, noise_sigma: float | None = None,
                   fuse_window_px: float = 2.0, noise_model: NoiseModel = "auto",
                   dihedral_ensemble: bool = False) -> list[np.ndarray]:
    """Denoise images with a trained model.

    Args:
        model: from `train_n2v`, `finetune_round2` or `load_checkpoint`.
        images: ``(H, W, 3)`` float32 RGB in ``[0, 1]`` (grayscale ``(H, W)`` / ``(H, W, 1)`` accepted).
        passes: K random maskings averaged; 0 = one pass on the unmasked image (as N2V predicts).
        seed: seeds the maskings.
        tile_px, margin_px: tiling (see `predict_tiled`).
        clean_sigma: images with an estimated noise std below this ([0, 1] units) are
            returned unchanged (clipped to [0, 1]); 0 denoises everything.
        fuse: blend the blind-spot prediction with the noisy pixel it ignored
            (`denoise.fusion.fuse_with_observation`); default: when the model is a
            blind-spot (round-1) model, ``model.blind_spot``.
        noise_sigma: noise std ([0, 1] units) for the fusion; default: estimated per image
            (`noise_model`).
        fuse_window_px: Gaussian window sigma (px) of the fusion's local variance.
        noise_model: how the fusion's noise level is estimated when `noise_sigma` is None
            (`fusion_noise_sigma`): ``"constant"``, one std per image; ``"curve"``,
            signal-dependent (Poisson-Gaussian) noise, a per-image `NoiseCurve` evaluated per
            pixel at the blind-spot prediction; ``"auto"`` picks one per image; ``"luma"``, one std read on
            the luma (`fusion_noise_sigma`).
        dihedral_ensemble: pass k runs on the k-th rotation/reflection (see `denoise_tensor`).

    Returns:
        Denoised images, float32 in ``[0, 1]``, each in the layout of its input.
    """
    if noise_model not in NOISE_MODELS:
        raise ValueError(f"noise_model must be one of {NOISE_MODELS}, got {noise_model!r}")
    device = next(model.unet.parameters()).device
    gen = torch.Generator(device=device).manual_seed(seed)
    out = []
    for i, img in enumerate(progress(images, desc="denoise", total=len(images))):
        x = image_to_tensor(img, name=f"image {i}")[None].to(device)
        sigma = estimate_noise_sigma(img)
        if sigma < clean_sigma:
            _log.info("image %d: estimated noise %.2f/255 < %.2f/255, left unchanged", i, sigma * 255,
                      clean_sigma * 255)
            out.append(tensor_to_image(x[0], like=img))
            continue
        y = denoise_tensor(model, x, passes=passes, generator=gen, tile_px=tile_px, margin_px=margin_px,
                           dihedral_ensemble=dihedral_ensemble)
        if model.blind_spot if fuse is None else fuse:
            s = fusion_noise_sigma(img, y, noise_model=noise_model) if noise_sigma is None else noise_sigma
            y = fuse_with_observation(y, x, noise_sigma=s, window_sigma_px=fuse_window_px)
        out.append(tensor_to_image(y[0], like=img))
    return out
