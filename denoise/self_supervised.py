"""Training and inference of the non-blind self-supervised methods on the N2V UNet.

`train_self_supervised` trains the same `N2VModel` (UNet, per-channel normalisation,
residual output ``x + alpha * UNet(x)``) as `denoise.n2v.train_n2v`, on the same
random patches, optimiser and learning-rate schedule, with another objective
(`N2VConfig.method`):

- ``"neighbor2neighbor"`` (`denoise.neighbor2neighbor`): the network maps one
  neighbour sub-image of a patch to the other, with the paper's regulariser; its
  weight ramps linearly from 0 to `N2VConfig.nb2nb_gamma` over the steps;
- ``"r2r"`` (`denoise.r2r`): the network maps ``y + alpha z`` to ``y - z / alpha``; the
  noise std of each image comes from `estimate_noise_sigma_clipped` unless given (clipping
  at 0 and 1 hides noise: over all patches the PCA estimate reads 22/255 on DTU photos with
  sigma 25/255 and about 10/255 on the temple's black background; its unclipped patches
  alone read 34-36/255 on the temple at sigma 50/255, where Foi's clipped-noise model fitted
  per intensity reads 47/255), or,
  where shot noise dominates, per pixel from the image's noise curve (`r2r_noise_std`;
  a constant std under-recorrupts the bright pixels and over-recorrupts the dark ones); at
  inference pass k runs on the k-th of the square's 8 rotations / reflections of the
  recorrupted image (`denoise.inference.dihedral`), an ensemble at no extra cost (DTU scan24,
  sigma 25, 8 passes: 29.27 -> 29.38 dB).

Both non-blind methods estimate the mean of the clipped noisy photo; `denoise_with_method` maps
their outputs back through the clipped-noise model (`denoise.clipping`) where the photo is clipped
(DTU sigma 25: 29.46 -> 30.54 dB; the temple ring at sigma 25: 26.75 -> 28.36 dB).

R2R's construction needs additive Gaussian noise: ``y + alpha z`` and ``y - z / alpha`` are independent
given the clean image only when ``y - x`` is Gaussian. Over a black region the photo's noise is clipped
at 0 (half its values are 0) and the target's noise depends on the input's: there R2R's network learns
something between denoising and the identity (on the temple ring at sigma 25 it passed the noise
through in the green and blue channels of the black background: std 9-13/255 out of the network
against 1.2-1.5/255 out of Neighbor2Neighbor's, before the clipped-noise inverse). Neighbor2Neighbor's
target is the other neighbour sub-image, whose noise is independent of the input's whatever its
distribution. `choose_objective` picks between them from the photos: Neighbor2Neighbor where a large
share of them lies in dark clipped regions (`denoise.clipping.dark_clipped_fraction`), R2R otherwise.

The model starts like N2V's, with the centre-cancelling head (`init_centre_cancelling`):
it starts as a smoother that ignores each pixel's own value and learns how much of
it to use. Starting from the identity instead (that input path zeroed) was far
slower on CPU budgets: 300 steps on two 64x64 synthetic images (sigma 25/255, width
8, depth 2), Neighbor2Neighbor 23.4 dB from the identity vs 31.6 dB, R2R 23.7 vs
32.4 dB (N2V: 30.8 dB). Neither network is blind-spot, so inference does not fuse
with the centre pixel. `train_with_method` trains any ``config.method`` (``"n2v"``: `train_n2v`);
`denoise_with_method` applies any method's model.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from denoise.clipping import (
    clipped_mean,
    clipped_sides,
    clipped_variance,
    dark_clipped_fraction,
    undo_clipping_bias,
)
from denoise.grouped_wiener import GroupedWienerConfig, grouped_wiener, pass_configs
from denoise.images import image_to_tensor, images_to_tensors, tensor_to_image
from denoise.inference import (
    CLEAN_SIGMA,
    MARGIN_PX,
    TILE_PX,
    NoiseModel,
    denoise_images,
    dihedral,
    mean_of_passes,
    predict_tiled,
    signal_dependent_curve,
)
from denoise.losses import neighbor2neighbor_loss
from denoise.model import N2VModel
from denoise.n2v import N2VConfig, StepBatch, new_model, optimise_unet, train_n2v
from denoise.neighbor2neighbor import neighbour_choice, neighbour_subsample
from denoise.noise_level import (
    chroma_subsampled_noise_sigma,
    constant_noise_sigma_luma,
    estimate_noise_sigma,
    estimate_noise_sigma_clipped,
)
from denoise.parallel import run_tasks
from denoise.patches import effective_patch_px, sample_patches
from denoise.r2r import recorrupt
from denoise.wiener import WienerConfig, dct_wiener
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.progress import progress, progress_bar

_log = logging.getLogger(__name__)

__all__ = ["MAX_DARK_CLIPPED_FOR_R2R", "ObjectiveChoice", "choose_objective", "denoise_one_pass", "denoise_with_method",
           "r2r_noise_std", "train_self_supervised", "train_with_method"]

#: `choose_objective`: R2R while at most this share of the photos' area (mean over the photos) lies in
#: dark clipped regions. Measured at sigma 25/255, 2000 steps, whole photos (PSNR of the denoised
#: training photos against the clean ones): DTU scan24 (0.03) R2R 30.52 dB, Neighbor2Neighbor 29.89;
#: the temple ring (0.60) R2R 27.12, Neighbor2Neighbor 34.29 (dark clipped regions 26.3 against 39.8 dB,
#: the rest 28.9 against 31.0). With those per-region errors the two break even near 0.05 of the area;
#: 0.2 switches only where the evidence is overwhelming (DTU at sigma 50 reads 0.06 and keeps R2R).
MAX_DARK_CLIPPED_FOR_R2R = 0.2


#: Gaussian blur (px) of the noisy image that stands in for the clean intensity where a
#: noise curve is evaluated: it cuts the noise about 7x (1 / (2 sqrt(pi) * 2)) while
#: keeping the shading that the variance follows.
INTENSITY_BLUR_PX = 2.0


def r2r_noise_std(img: np.ndarray, *, noise_model: NoiseModel = "auto") -> float | torch.Tensor:
    """The noise std that R2R recorrupts `img` with: one number, or a per-pixel map.

    Args:
        img: ``(H, W, 3)`` RGB (or gray) in ``[0, 1]``.
        noise_model: ``"constant"``: `estimate_noise_sigma_clipped` (the unclipped patches' PCA estimate, or
            the clipped-noise fit where that is larger: a dark photo at a high noise level);
            ``"curve"``: the image's `NoiseCurve` evaluated at its `INTENSITY_BLUR_PX`
            Gaussian blur; ``"auto"``: the constant read on the luma where the photo's noise is
            chroma-subsampled (`denoise.noise_level.chroma_subsampled_noise_sigma`: a JPEG's colour
            patches hold no fine noise, and a curve read on them would too), else the curve where its
            signal-dependent term dominates at the median intensity
            (`denoise.inference.signal_dependent_curve`, the N2V fusion's rule), else the constant;
            ``"luma"``: the constant read on the luma whatever the colour patches read
            (`denoise.noise_level.constant_noise_sigma_luma`), for a set of photos whose noise
            `denoise.pixel_shuffle.choose_stride` found chroma-subsampled: their pixel-shuffled sub-images'
            colour patches need not read under `denoise.noise_level.CHROMA_DEFICIT_RATIO` of it as the photos do.

    Returns:
        A float, or a ``[C, H, W]`` float32 tensor (``[0, 1]`` units).
    """
    if noise_model == "luma":
        return constant_noise_sigma_luma(img)
    if noise_model == "auto":
        luma = chroma_subsampled_noise_sigma(img)
        if luma is not None:
            return luma
    curve = signal_dependent_curve(img, noise_model)
    if curve is None:  # "auto" has read the luma above
        return estimate_noise_sigma_clipped(img, read_luma=noise_model != "auto")
    blurred = cv2.GaussianBlur(np.ascontiguousarray(img, dtype=np.float32), (0, 0), INTENSITY_BLUR_PX)
    return curve.sigma_at(image_to_tensor(blurred.reshape(img.shape)))


#: Noise std of images: one number for all, one per image (a number, or a ``[C, H, W]`` per-pixel map as
#: `r2r_noise_std` gives), or None (estimated).
NoiseStd = float | Sequence[float | torch.Tensor] | None


def _sigmas(images: Sequence[np.ndarray], noise_sigma: NoiseStd, noise_model: NoiseModel) -> list[float | torch.Tensor]:
    if noise_sigma is None:
        return [r2r_noise_std(im, noise_model=noise_model) for im in images]
    if np.isscalar(noise_sigma):
        return [float(noise_sigma)] * len(images)
    sig = [s if isinstance(s, torch.Tensor) else float(s) for s in noise_sigma]
    if len(sig) != len(images):
        raise InputError(f"{len(sig)} noise levels for {len(images)} images")
    return sig


def _describe(sig: float | torch.Tensor) -> str:
    """``24.9`` for one std, ``~18.2`` for the median of a per-pixel map (``/255``)."""
    if isinstance(sig, torch.Tensor):
        return f"~{255 * float(sig.median()):.1f}"
    return f"{255 * sig:.1f}"


@dataclass(frozen=True)
class ObjectiveChoice:
    """`choose_objective`'s answer.

    Attributes:
        method: "r2r" or "neighbor2neighbor".
        dark_clipped_fraction: mean over the photos of `denoise.clipping.dark_clipped_fraction`.
    """

    method: Literal["r2r", "neighbor2neighbor"]
    dark_clipped_fraction: float


def choose_objective(images: Sequence[np.ndarray], *, max_dark_clipped: float = MAX_DARK_CLIPPED_FOR_R2R
                     ) -> ObjectiveChoice:
    """R2R, or Neighbor2Neighbor where more than `max_dark_clipped` of the photos' area lies in dark
    clipped regions (module docstring; `MAX_DARK_CLIPPED_FOR_R2R`)."""
    if not images:
        raise InputError("no images to choose a denoising objective for")
    frac = float(np.mean([dark_clipped_fraction(im) for im in images]))
    method = "neighbor2neighbor" if frac > max_dark_clipped else "r2r"
    _log.info("denoising objective: %s (%.0f %% of the photos' area is dark and clipped; R2R up to %.0f %%)",
              method, 100 * frac, 100 * max_dark_clipped)
    return ObjectiveChoice(method, frac)


def train_with_method(images: Sequence[np.ndarray], config: N2VConfig, *, seed: int = 0,
                      model: N2VModel | None = None, device: str | torch.device = "cpu",
                      noise_model: NoiseModel = "auto", noise_sigma: NoiseStd = None) -> N2VModel:
    """Train the UNet with ``config.method``: `denoise.n2v.train_n2v` or `train_self_supervised`.

    Arguments as `train_n2v` (`noise_model`, `noise_sigma`: R2R only, as `train_self_supervised`'s);
    apply the result with `denoise_with_method` and the same `config`, `noise_model` and `noise_sigma`.
    """
    if config.method == "n2v":
        return train_n2v(images, config, seed=seed, model=model, device=device)
    return train_self_supervised(images, config, seed=seed, model=model, device=device, noise_model=noise_model,
                                 noise_sigma=noise_sigma)


def train_self_supervised(images: Sequence[np.ndarray], config: N2VConfig, *, seed: int = 0,
                          model: N2VModel | None = None,
                          noise_sigma: NoiseStd = None,
                          device: str | torch.device = "cpu", noise_model: NoiseModel = "auto") -> N2VModel:
    """Train the UNet with Neighbor2Neighbor or Recorrupted-to-Recorrupted (``config.method``).

    Args:
        images: ``(H, W, 3)`` float32 RGB in ``[0, 1]``; sizes may differ (each side >= 2 px).
        config: training options; ``method`` must be ``"neighbor2neighbor"`` or ``"r2r"``.
        seed: seeds the weights, the patches, the sub-sampling / recorruption noise.
        model: continue training this model instead of a new one.
        noise_sigma: ``"r2r"`` only: noise std per image (a number, or a per-pixel map as `r2r_noise_std`
            gives), or one for all, ``[0, 1]`` units; default: `r2r_noise_std` of each image with `noise_model`.
        device: torch device of the training (the model is moved there and returned there).
        noise_model: ``"r2r"`` only, when `noise_sigma` is not given (see `r2r_noise_std`).

    Returns:
        The trained `N2VModel` (eval mode, on `device`, ``blind_spot=False``), per-step losses in
        ``history``.

    Raises:
        InputError: empty list, non-finite values, images below 2x2 px, wrong number of sigmas.
    """
    if config.method not in ("neighbor2neighbor", "r2r"):
        raise ValueError(f"train_self_supervised trains neighbor2neighbor or r2r, not {config.method!r}")
    tensors = images_to_tensors(images)
    rng = np.random.default_rng(seed)
    device = torch.device(device)
    gen = torch.Generator(device=device).manual_seed(seed)
    if model is None:
        model = new_model(config, tensors, seed=seed)
    model.unet.to(device)
    model.blind_spot = False
    patch = effective_patch_px(tensors, config.patch_px)
    if patch < 2:
        raise InputError(f"images must be at least 2x2 px for {config.method}, smallest side is {patch}")
    mean = torch.tensor(model.mean).reshape(3, 1, 1)
    std = torch.tensor(model.std).reshape(3, 1, 1)
    normed = [((t - mean) / std).to(device) for t in tensors]
    paired = None
    if config.method == "r2r":
        sig = _sigmas(images, noise_sigma, noise_model)
        _log.info("r2r noise std per image (/255; ~: median of a per-pixel map): %s",
                  " ".join(_describe(s) for s in sig))
        # Per-image std in normalised units, as a map cropped with the patches (a constant one is
        # broadcast, not copied).
        paired = [(torch.as_tensor(s, dtype=torch.float32) / std).to(device).expand(3, *t.shape[-2:])
                  for s, t in zip(sig, tensors, strict=True)]
    def r2r_loss(unet: torch.nn.Module, inp: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
        return torch.mean((inp + model.alpha * unet(inp) - tgt) ** 2)

    def step_batch(step: int) -> StepBatch:
        batch, extra = sample_patches(normed, patch_px=patch, batch_size=config.batch_size, rng=rng,
                                      paired=paired, augment=config.augment)
        if config.method == "neighbor2neighbor":
            choice = neighbour_choice(batch.shape[0], patch, patch, generator=gen, device=device)
            gamma = config.nb2nb_gamma * (step + 1) / config.steps

            def nb2nb_loss(unet: torch.nn.Module, batch: torch.Tensor, choice: torch.Tensor) -> torch.Tensor:
                g1, g2 = neighbour_subsample(batch, choice)
                with torch.no_grad():
                    full1, full2 = neighbour_subsample(batch + model.alpha * unet(batch), choice)
                return neighbor2neighbor_loss(g1 + model.alpha * unet(g1), g2, full1, full2, gamma=gamma)

            return StepBatch((batch, choice), nb2nb_loss)
        return StepBatch(recorrupt(batch, extra, alpha=config.r2r_alpha, generator=gen), r2r_loss)

    return optimise_unet(model, config, step_batch, desc=config.method)


def denoise_one_pass(model: N2VModel, images: Sequence[np.ndarray], *, tile_px: int = TILE_PX,
                     margin_px: int = MARGIN_PX, clean_sigma: float = CLEAN_SIGMA) -> list[np.ndarray]:
    """One pass of a non-blind network over each whole image (Neighbor2Neighbor, multi-view Noise2Noise).

    Images whose estimated noise is below `clean_sigma` are returned unchanged (clipped).
    Returns float32 images in ``[0, 1]``, each in the layout of its input.
    """
    device = next(model.unet.parameters()).device
    model.unet.eval()

    def one(i: int) -> np.ndarray:
        img = images[i]
        x = image_to_tensor(img, name=f"image {i}")[None].to(device)
        if estimate_noise_sigma(img) >= clean_sigma:
            x = predict_tiled(model, x, tile_px=tile_px, margin_px=margin_px)
        bar.update(1)
        return tensor_to_image(x[0], like=img)

    # The images on the denoiser's threads (`denoise.parallel`), one torch thread each.
    with progress_bar(desc="denoise", total=len(images)) as bar:
        return run_tasks(one, range(len(images)), device=device)


def denoise_with_method(model: N2VModel, images: Sequence[np.ndarray], config: N2VConfig, *, passes: int = 8,
                        seed: int = 0, noise_sigma: NoiseStd = None,
                        tile_px: int = TILE_PX, margin_px: int = MARGIN_PX, clean_sigma: float = CLEAN_SIGMA,
                        noise_model: NoiseModel = "auto", undo_clipping: bool = True,
                        wiener: WienerConfig | None = None,
                        grouped: GroupedWienerConfig | None = None) -> list[np.ndarray]:
    """Denoise `images` with a model trained by ``config.method``.

    - ``"n2v"``: `denoise.inference.denoise_images` (K maskings, centre-pixel fusion);
    - ``"neighbor2neighbor"``: one pass of the network on the whole image (`passes` unused);
    - ``"r2r"``: mean of the network over ``max(passes, 1)`` recorruptions ``y + alpha z_k``
      (``z_k ~ N(0, sigma^2)``, sigma per image or pixel as in training), pass k on the ``k % 8``-th
      rotation / reflection of the recorrupted image (`denoise.inference.dihedral`, undone after).

    Args:
        model: from `train_n2v` / `train_self_supervised` with this `config`.
        images: ``(H, W, 3)`` float32 RGB in ``[0, 1]`` (gray accepted).
        config: the training config (its ``method`` and ``r2r_alpha``).
        passes: see above.
        seed: seeds the maskings / recorruptions.
        noise_sigma: ``"r2r"``: noise std per image or one for all (default: estimated as in training);
            ``"n2v"``: the fusion's noise std (see `denoise_images`).
        tile_px, margin_px: tiling (`denoise.inference.predict_tiled`).
        clean_sigma: images whose estimated noise is below this are returned unchanged.
        noise_model: ``"n2v"``: the fusion's (see `denoise_images`); ``"r2r"``: the
            recorruption's, as in training (see `r2r_noise_std`).
        undo_clipping: ``"r2r"`` and ``"neighbor2neighbor"``: map each output through the inverse of
            the clipped-noise mean (`denoise.clipping.undo_clipping_bias`, with the std of
            `r2r_noise_std` or `noise_sigma`) on the sides where the noisy photo is clipped: the
            networks estimate the mean of the clipped photo, which is biased near 0 and 1. Not for
            ``"n2v"``: the inverse's slope (above 1 near 0 and 1) amplifies the noise its fused
            output keeps there; on the DTU scan24 photos at sigma 25 (`fast` preset, 2 passes) it
            gave +0.25 dB but SSIM -0.015 and LPIPS +0.007.
        wiener: refine each network output with the sliding-window DCT Wiener step (`denoise.wiener`: the
            noisy photo shrunk by the gains the output implies, at the noise std above), before the
            clipping correction; None: the network's output as it is.
        grouped: then the grouped Wiener step (`denoise.grouped_wiener`: similar patches of the noisy photo
            filtered together with the statistics of the photo so far, at the same noise std), followed by
            the clipping correction again; None: off.

    Returns:
        Denoised images, float32 in ``[0, 1]``, each in the layout of its input.
    """
    if passes < 0:
        raise ValueError(f"passes must be >= 0, got {passes}")
    if config.method == "n2v":
        if noise_sigma is not None and not np.isscalar(noise_sigma):
            raise InputError("n2v's fusion takes one noise_sigma for all images")
        out = denoise_images(model, images, passes=passes, seed=seed, tile_px=tile_px, margin_px=margin_px,
                             clean_sigma=clean_sigma, noise_sigma=noise_sigma, noise_model=noise_model)
        if wiener is None and grouped is None:
            return out
        stds = [torch.as_tensor(s, dtype=torch.float32) for s in _sigmas(images, noise_sigma, noise_model)]
        out = out if wiener is None else _refined(images, out, stds, clean_sigma, wiener)
        for cfg in [] if grouped is None else pass_configs(grouped):
            out = _grouped(images, out, stds, clean_sigma, cfg)
        return out
    device = next(model.unet.parameters()).device

    def sigmas() -> list[torch.Tensor]:
        return [torch.as_tensor(s, dtype=torch.float32).to(device) for s in _sigmas(images, noise_sigma, noise_model)]

    if config.method == "neighbor2neighbor":
        out = denoise_one_pass(model, images, tile_px=tile_px, margin_px=margin_px, clean_sigma=clean_sigma)
        sig = sigmas()
        out = out if wiener is None else _refined(images, out, sig, clean_sigma, wiener)
        return _then_grouped(images, out, sig, clean_sigma, undo_clipping, grouped)
    sig = sigmas()
    gen = torch.Generator(device=device).manual_seed(seed)
    model.unet.eval()
    out = []
    with torch.no_grad():
        for i, img in enumerate(progress(images, desc="denoise", total=len(images))):
            x = image_to_tensor(img, name=f"image {i}")[None].to(device)
            if estimate_noise_sigma(img) < clean_sigma:
                out.append(tensor_to_image(x[0], like=img))
                continue
            def draw(d: int, x: torch.Tensor = x, s: torch.Tensor = sig[i]) -> torch.Tensor:
                z = torch.randn(x.shape, generator=gen, device=device, dtype=x.dtype)
                return dihedral(x + config.r2r_alpha * s * z, d)

            def predict(d: int, recorrupted: torch.Tensor) -> torch.Tensor:
                pred = predict_tiled(model, recorrupted, tile_px=tile_px, margin_px=margin_px)
                return dihedral(pred, d, inverse=True)

            out.append(tensor_to_image(mean_of_passes(x, max(passes, 1), draw, predict)[0], like=img))
    out = out if wiener is None else _refined(images, out, sig, clean_sigma, wiener)
    return _then_grouped(images, out, sig, clean_sigma, undo_clipping, grouped)


def _then_grouped(noisy: Sequence[np.ndarray], out: list[np.ndarray], sigmas: Sequence[torch.Tensor],
                  clean_sigma: float, undo_clipping: bool, grouped: GroupedWienerConfig | None) -> list[np.ndarray]:
    """The clipping correction (`undo_clipping`), then, with `grouped`, the grouped Wiener step on the
    corrected photos as pilots, in the clipped photo's domain (`_grouped`), and the correction once more;
    `grouped.passes` times, each pass's output the next one's pilot (`pass_configs`)."""
    out = _undo_clipping(noisy, out, sigmas, clean_sigma) if undo_clipping else out
    for cfg in [] if grouped is None else pass_configs(grouped):
        out = _grouped(noisy, out, sigmas, clean_sigma, cfg, clipped_domain=undo_clipping)
        out = _undo_clipping(noisy, out, sigmas, clean_sigma) if undo_clipping else out
    return out


def _grouped(noisy: Sequence[np.ndarray], out: list[np.ndarray], sigmas: Sequence[torch.Tensor], clean_sigma: float,
             config: GroupedWienerConfig, *, clipped_domain: bool = False) -> list[np.ndarray]:
    """`grouped_wiener` of each noisy photo with its current estimate as the pilot, clipped to [0, 1], one photo
    per thread (`run_tasks`); images returned unchanged as clean (noise below `clean_sigma`) stay so.

    With `clipped_domain`, a photo clipped at 0 or 1 (`clipped_sides`) is filtered where its noisy values live:
    the pilot (a clean-value estimate) becomes the clipped photo's expected value (`clipped_mean`) and the
    noise std the clipped noise's (`clipped_variance`, smaller near 0 and 1), so the noisy patches, the
    pilot's statistics and the noise model agree; the output is then an estimate of the clipped mean, for
    `undo_clipping_bias`. On DTU scan24 at sigma 25 the clean-value pilot instead lost 8 dB in the black
    regions (docs/bench/denoise_real.md, "The grouped Wiener step")."""
    def one(item: tuple[np.ndarray, np.ndarray, torch.Tensor]) -> np.ndarray:
        img, den, sigma = item
        if estimate_noise_sigma(img) < clean_sigma:
            return den
        y, d = np.asarray(img, np.float32), np.asarray(den, np.float32)
        gray = y.ndim == 2 or y.shape[-1] == 1
        std = _std_map(sigma, gray)
        low, high = clipped_sides(img) if clipped_domain else (False, False)
        if low or high:
            x, s = image_to_tensor(den), sigma.detach().cpu()
            d = tensor_to_image(clipped_mean(x, s, low=low, high=high), like=den)
            std = tensor_to_image(clipped_variance(x, s, low=low, high=high).sqrt(), like=den)
        if gray:
            y, d = y.reshape(y.shape[:2]), np.asarray(d).reshape(y.shape[:2])
            std = std if np.ndim(std) < 2 else np.asarray(std).reshape(y.shape[:2])
        x = grouped_wiener(y, d, std, config)
        return np.clip(x, 0.0, 1.0).astype(np.float32).reshape(np.shape(den))

    return run_tasks(one, list(zip(noisy, out, sigmas, strict=True)))


def _std_map(sigma: torch.Tensor, gray: bool) -> np.ndarray:
    """A noise std as the numpy Wiener steps take it: one number, ``(H, W, 3)``, or ``(H, W)`` for a gray photo
    (``[C, H, W]`` per-pixel maps moved channel-last; a gray photo's is the channels' RMS)."""
    s = sigma.detach().cpu().numpy()
    if s.ndim == 3:
        s = np.sqrt(np.mean(s ** 2, axis=0)) if gray else np.moveaxis(s, 0, -1)
    return s


def _refined(noisy: Sequence[np.ndarray], out: list[np.ndarray], sigmas: Sequence[torch.Tensor], clean_sigma: float,
             config: WienerConfig) -> list[np.ndarray]:
    """`dct_wiener` of each noisy photo with its network output as the pilot, clipped to [0, 1]; images returned
    unchanged as clean (noise below `clean_sigma`) stay so."""
    refined = []
    for img, den, sigma in zip(noisy, out, sigmas, strict=True):
        if estimate_noise_sigma(img) < clean_sigma:
            refined.append(den)
            continue
        y, d = np.asarray(img, np.float32), np.asarray(den, np.float32)
        gray = y.ndim == 2 or y.shape[-1] == 1
        if gray:
            y, d = y.reshape(y.shape[:2]), d.reshape(y.shape[:2])
        x = dct_wiener(y, d, _std_map(sigma, gray), config)
        refined.append(np.clip(x, 0.0, 1.0).astype(np.float32).reshape(np.shape(den)))
    return refined


def _undo_clipping(noisy: Sequence[np.ndarray], out: list[np.ndarray], sigmas: Sequence[torch.Tensor],
                   clean_sigma: float) -> list[np.ndarray]:
    """`undo_clipping_bias` on each denoised image, on the sides its noisy photo is clipped; images
    returned unchanged as clean (noise below `clean_sigma`) stay so."""
    fixed = []
    for img, den, sigma in zip(noisy, out, sigmas, strict=True):
        low, high = clipped_sides(img)
        if not (low or high) or estimate_noise_sigma(img) < clean_sigma:
            fixed.append(den)
            continue
        x = undo_clipping_bias(image_to_tensor(den).to(sigma.device), sigma, low=low, high=high)
        fixed.append(tensor_to_image(x, like=den))
    return fixed
