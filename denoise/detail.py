"""The splat's training target: a denoised photo with part of its noisy photo's finest band added back.

A single-image denoiser removes noise and fine texture together, and what it keeps of the texture differs
from view to view (each view's guess). A splat trained on such photos averages those guesses into a blur: on
`llff_like` (seed 0, 256x192) the `default` product's splat rendered its own training views at LPIPS 0.230
against 0.133 for the photos it trained on; on DTU scan24 at sigma 25 at 0.122 against 0.071, where a splat of
the clean photos reproduces them at 0.041 (docs/bench/pipeline.md, "The noisy photos' finest band in the
splat's target").

The noisy photo's finest band holds that texture, the same in every view, plus noise that differs in every
view. Adding a fraction ``w`` of the band the denoiser removed,

    target = denoised + w * highpass_s(noisy - denoised),   highpass_s(x) = x - G_s * x,

hands the splat the texture; the splat, fitting a dozen views with one set of Gaussians, keeps what the views
agree on and averages the added noise. ``G_s`` is a Gaussian blur of standard deviation ``s`` pixels
(OpenCV's, radius ``int(6 s) | 1 // 2``, mirrored borders); the target is clipped to [0, 1], the range the
splat trains on. ``w = 0`` is the denoised photo itself.

The band adds noise of standard deviation about ``w * sigma`` to each view. Above a reference noise level the
weight is scaled down so that this stays at ``w * reference_std``: ``w_eff = w * min(1, reference_std /
sigma)``, with ``sigma`` the photo's noise std as the denoiser estimates it. On DTU scan24 at sigma 50/255 a
fixed 0.3 cost 0.54 dB held out where at sigma 25 it cost 0.06-0.15 (docs/bench/pipeline.md).

In a dark clipped region (a black background under noise clipped at 0, `denoise.clipping.dark_clipped_mask`)
the band is left out: there the noise is rectified, not zero-mean, the band holds no texture, and the splat
kept some of it (the temple ring with the true cameras: SSIM 0.740 against 0.794 without the band).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["NoisyDetail", "gaussian_kernel_size", "noisy_detail_target", "noisy_detail_weight"]


@dataclass(frozen=True)
class NoisyDetail:
    """How much of the noisy photo's finest band the splat's target takes back.

    Attributes:
        weight: ``w`` in [0, 1]: the fraction of ``highpass(noisy - denoised)`` added to the denoised photo
            (0: none, the denoised photo; 1: the noisy photo's whole finest band).
        sigma_px: ``s`` > 0, the standard deviation in pixels of the Gaussian whose complement is the band.
        reference_std: the noise std ([0, 1] units) above which the weight is scaled by ``reference_std /
            sigma`` (`noisy_detail_weight`); None: never scaled.
        skip_dark_clipped: True: no band in the noisy photo's dark clipped regions
            (`denoise.clipping.dark_clipped_mask`); False: the band everywhere.
    """

    weight: float = 0.0
    sigma_px: float = 1.0
    reference_std: float | None = 25.0 / 255.0
    skip_dark_clipped: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= float(self.weight) <= 1.0:
            raise ValueError(f"NoisyDetail.weight must be in [0, 1], got {self.weight}")
        if not float(self.sigma_px) > 0.0:
            raise ValueError(f"NoisyDetail.sigma_px must be > 0, got {self.sigma_px}")
        if self.reference_std is not None and not float(self.reference_std) > 0.0:
            raise ValueError(f"NoisyDetail.reference_std must be > 0 or None, got {self.reference_std}")


def noisy_detail_weight(detail: NoisyDetail, noise_std: float | None) -> float:
    """The weight for a photo whose noise std is `noise_std` ([0, 1] units; None or <= 0: unknown, the
    weight as set): ``weight * min(1, reference_std / noise_std)``."""
    if detail.reference_std is None or noise_std is None or not noise_std > 0.0:
        return float(detail.weight)
    return float(detail.weight) * min(1.0, float(detail.reference_std) / float(noise_std))


def gaussian_kernel_size(sigma_px: float) -> int:
    """The odd kernel width `noisy_detail_target` blurs with: ``int(6 * sigma_px) | 1`` (7 for 1 px)."""
    return int(6.0 * sigma_px) | 1


def noisy_detail_target(denoised: np.ndarray, noisy: np.ndarray, detail: NoisyDetail,
                        noise_std: float | None = None) -> np.ndarray:
    """``clip(denoised + w * (r - G_s * r), 0, 1)`` with ``r = noisy - denoised``, the band left out in dark
    clipped regions with `detail.skip_dark_clipped` (module docstring).

    Args:
        denoised: `(H, W, 3)` float image in [0, 1].
        noisy: `(H, W, 3)` float image in [0, 1], the same view.
        detail: the weight and blur ``s``.
        noise_std: the noisy photo's noise std; ``w = noisy_detail_weight(detail, noise_std)``.

    Returns:
        `(H, W, 3)` float32 image in [0, 1]; `denoised` (as float32) when ``w = 0``.

    Raises:
        ValueError: the two images differ in shape or are not `(H, W, 3)`.
    """
    import cv2

    if denoised.shape != noisy.shape or denoised.ndim != 3 or denoised.shape[2] != 3:
        raise ValueError(f"noisy_detail_target: denoised {denoised.shape} and noisy {noisy.shape} must both "
                         "be (H, W, 3)")
    d = np.asarray(denoised, np.float32)
    weight = noisy_detail_weight(detail, noise_std)
    if weight == 0.0:
        return d.copy()
    residual = np.asarray(noisy, np.float32) - d
    k = gaussian_kernel_size(detail.sigma_px)
    band = residual - cv2.GaussianBlur(residual, (k, k), detail.sigma_px, borderType=cv2.BORDER_REFLECT_101)
    if detail.skip_dark_clipped:
        from denoise.clipping import dark_clipped_mask  # torch: resolved when called

        band[dark_clipped_mask(noisy)] = 0.0
    return np.clip(d + np.float32(weight) * band, 0.0, 1.0)
