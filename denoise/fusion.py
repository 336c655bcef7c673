"""Fusing a blind-spot prediction with the noisy pixel it ignored (a local Wiener / MMSE step).

A Noise2Void network predicts each pixel from its neighbours only: its output
``mu`` is an estimate of the clean value *before* looking at the pixel's own
noisy observation ``y``. Detail that the neighbours cannot predict (fine
texture, one-pixel features) is therefore lost. Laine et al. 2019 ("High-Quality
Self-Supervised Deep Image Denoising") recover it with a Bayesian posterior
mean: with a Gaussian prior ``x ~ N(mu, v_prior)`` and Gaussian noise
``y = x + n, n ~ N(0, v_noise)``,

    x_hat = mu + v_prior / (v_prior + v_noise) * (y - mu).

They let the network predict ``v_prior``; we estimate it locally instead, from
the residual ``r = y - mu`` whose local second moment is ``v_prior + v_noise``:
``v_prior = max(G * r^2 - v_noise, 0)`` with a Gaussian window ``G``
(the adaptive Wiener filter of Lee 1980 applied to the residual). Where the
network explains the image well (flat areas) ``v_prior ~ 0`` and the output is
``mu``; in texture the observation is blended back in.

``v_noise`` is the noise variance in ``[0, 1]`` units, a scalar or a per-pixel map
(signal-dependent noise); `denoise.inference.denoise_images` estimates it per image
(`denoise.noise_level.estimate_noise_sigma_pca`, or a `NoiseCurve` evaluated at ``mu``).
An over-estimate errs towards ``mu``, an under-estimate towards ``y``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from denoise.filters import gaussian_blur
from mvgeo.common.errors import check_shape


def fuse_with_observation(prior_mean: Tensor, noisy: Tensor, *, noise_sigma: float | Tensor,
                          window_sigma_px: float = 2.0) -> Tensor:
    """Posterior-mean blend of a blind-spot prediction and the noisy observation, per channel.

    Args:
        prior_mean: ``[B, C, H, W]`` blind-spot prediction ``mu`` (``[0, 1]`` units).
        noisy: ``[B, C, H, W]`` observation ``y``.
        noise_sigma: noise standard deviation, a float or a tensor broadcastable to
            ``[B, C, H, W]`` (e.g. ``[B, 1, 1, 1]`` per image); ``0`` returns `noisy`.
        window_sigma_px: standard deviation of the Gaussian window (pixels) over which the
            residual's second moment is averaged; larger is steadier, smaller adapts to edges.

    Returns:
        ``[B, C, H, W]``, dtype of `prior_mean` (not clipped).
    """
    check_shape(prior_mean, ["B", "C", "H", "W"], "prior_mean")
    check_shape(noisy, list(prior_mean.shape), "noisy")
    if not window_sigma_px > 0:
        raise ValueError(f"window_sigma_px must be > 0, got {window_sigma_px}")
    v_noise = torch.as_tensor(noise_sigma, dtype=prior_mean.dtype, device=prior_mean.device) ** 2
    r = noisy - prior_mean
    second_moment = gaussian_blur(r * r, sigma=window_sigma_px)
    v_prior = (second_moment - v_noise).clamp_min(0.0)
    denom = v_prior + v_noise
    gain = torch.where(denom > 0, v_prior / denom.clamp_min(torch.finfo(denom.dtype).tiny), torch.ones_like(denom))
    return prior_mean + gain * r
