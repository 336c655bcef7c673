"""Sensor noise effects: additive Gaussian, signal-dependent Poisson-Gaussian, and Poisson-Gaussian on a Bayer
mosaic as demosaicing leaves it (spatially correlated)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_synth.effects.registry import EffectContext, register_effect
from data_synth.schema import join_key, spec_field
from mvgeo.common.errors import ConfigError


def _one_of(a: float | None, b: float | None, names: tuple[str, str], key: str, path: Path | None) -> None:
    if (a is None) == (b is None):
        raise ConfigError(f"give exactly one of {names[0]} and {names[1]}", key=join_key(key, names[0]), path=path,
                          expected=f"{names[0]} (in [0, 1] units) or {names[1]} (in 8-bit units)")


@dataclass(frozen=True)
class GaussianParams:
    sigma: float | None = spec_field(None, range=(0.0, 1.0), doc="std in [0, 1] image units")
    sigma_8bit: float | None = spec_field(None, range=(0.0, 255.0), doc="std in 8-bit units (25 = 25/255)")
    clip: bool = spec_field(True, doc="clip the result to [0, 1] (a sensor saturates)")

    def validated(self, *, key: str, path: Path | None) -> GaussianParams:
        _one_of(self.sigma, self.sigma_8bit, ("sigma", "sigma_8bit"), key, path)
        return self

    @property
    def sigma01(self) -> float:
        return float(self.sigma) if self.sigma is not None else float(self.sigma_8bit) / 255.0


@register_effect("gaussian", GaussianParams)
def gaussian(image: np.ndarray, params: GaussianParams, ctx: EffectContext, rng: np.random.Generator) -> np.ndarray:
    """Additive white Gaussian noise, y = x + N(0, sigma^2), per pixel and channel."""
    out = image + rng.normal(scale=params.sigma01, size=image.shape).astype(np.float32)
    return np.clip(out, 0.0, 1.0) if params.clip else out


@dataclass(frozen=True)
class PoissonGaussianParams:
    gain: float = spec_field(0.01, range=(1e-6, 1.0),
                             doc="shot-noise gain a: Var[y | x] = a * x + sigma^2 (a = 1 / full-well electrons)")
    read_sigma: float | None = spec_field(None, range=(0.0, 1.0), doc="read-noise std in [0, 1] units")
    read_sigma_8bit: float | None = spec_field(None, range=(0.0, 255.0), doc="read-noise std in 8-bit units")
    clip: bool = spec_field(True, doc="clip the result to [0, 1]")

    def validated(self, *, key: str, path: Path | None) -> PoissonGaussianParams:
        _one_of(self.read_sigma, self.read_sigma_8bit, ("read_sigma", "read_sigma_8bit"), key, path)
        return self

    @property
    def read_sigma01(self) -> float:
        return float(self.read_sigma) if self.read_sigma is not None else float(self.read_sigma_8bit) / 255.0


@register_effect("poisson_gaussian", PoissonGaussianParams)
def poisson_gaussian(image: np.ndarray, params: PoissonGaussianParams, ctx: EffectContext,
                     rng: np.random.Generator) -> np.ndarray:
    """Signal-dependent sensor noise, y = a * Poisson(x / a) + N(0, sigma^2): Var[y | x] = a x + sigma^2."""
    a = params.gain
    electrons = rng.poisson(np.maximum(image, 0.0).astype(np.float64) / a)
    out = (a * electrons + rng.normal(scale=params.read_sigma01, size=image.shape)).astype(np.float32)
    return np.clip(out, 0.0, 1.0) if params.clip else out


#: Colour (0 R, 1 G, 2 B) of each site of the 2x2 RGGB Bayer cell: rows (even, odd) x columns (even, odd).
RGGB = np.array([[0, 1], [1, 2]])


def bayer_channel_of(height: int, width: int) -> np.ndarray:
    """(H, W) int: the colour each pixel of an RGGB mosaic samples (`RGGB`, tiled from the top-left)."""
    return np.tile(RGGB, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


def bilinear_demosaic(mosaic: np.ndarray) -> np.ndarray:
    """(H, W) RGGB mosaic -> (H, W, 3): each colour's samples interpolated bilinearly from its own sites.

    A colour present at a pixel is kept; a missing one is the mean of that colour's samples among the
    pixel's 8 neighbours (2 or 4 of them). Normalised convolution, so the image border has no fall-off.
    Linear in the mosaic: demosaicing a sum is the sum of the demosaiced parts.
    """
    from mvgeo.common.deps import cv2

    m = np.asarray(mosaic, np.float64)
    chan = bayer_channel_of(*m.shape)
    kernel = np.array([[1.0, 1.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    out = np.empty(m.shape + (3,), np.float64)
    for c in range(3):
        site = (chan == c).astype(np.float64)
        total = cv2.filter2D(m * site, cv2.CV_64F, kernel, borderType=cv2.BORDER_CONSTANT)
        count = cv2.filter2D(site, cv2.CV_64F, kernel, borderType=cv2.BORDER_CONSTANT)
        out[:, :, c] = np.where(site > 0, m, total / np.maximum(count, 1e-12))
    return out


@dataclass(frozen=True)
class BayerNoiseParams(PoissonGaussianParams):
    """`PoissonGaussianParams`, drawn at each sensor site of the Bayer mosaic (`bayer_noise`)."""


@register_effect("bayer_noise", BayerNoiseParams)
def bayer_noise(image: np.ndarray, params: BayerNoiseParams, ctx: EffectContext,
                rng: np.random.Generator) -> np.ndarray:
    """Poisson-Gaussian noise of a Bayer sensor as bilinear demosaicing leaves it: correlated in space.

    ``y = x + D(n)``: ``n`` is Poisson-Gaussian noise on the RGGB mosaic of ``x`` (each site samples one
    colour; ``Var[n] = a x_site + sigma^2``) and ``D`` is `bilinear_demosaic`. A camera's raw-to-RGB step
    interpolates each missing colour from neighbouring noisy sites, so its noise is no longer independent
    from pixel to pixel, which is what pixel-wise self-supervised denoisers (N2V, R2R, Neighbor2Neighbor)
    assume. Bilinear demosaicing fills each colour from that colour's own sites, so the three channels' noises
    stay independent of each other (a camera's edge-aware demosaicing, e.g. VNG, mixes them too; not
    simulated). ``D`` is linear, so only the noise passes through it: the image keeps its
    full colour detail and a difference from the clean image is the noise alone (a real demosaicing also
    blurs and fringes the image; that is not simulated). Per pixel the noise std is the site's at the
    sampled colour and 1/2 or 1/4 of the variance elsewhere (the mean of 2 or 4 sites).
    """
    x = np.maximum(np.asarray(image, np.float64), 0.0)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"bayer_noise needs an (H, W, 3) RGB image, got shape {x.shape}")
    H, W = x.shape[:2]
    chan = bayer_channel_of(H, W)
    site = np.take_along_axis(x, chan[:, :, None], axis=2)[:, :, 0]
    a = params.gain
    n = a * rng.poisson(site / a) - site + rng.normal(scale=params.read_sigma01, size=site.shape)
    out = (x + bilinear_demosaic(n)).astype(np.float32)
    return np.clip(out, 0.0, 1.0) if params.clip else out
