"""Photometric effects: per-view exposure / white balance and lens vignetting."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data_synth.effects.registry import EffectContext, register_effect
from data_synth.schema import spec_field


@dataclass(frozen=True)
class ExposureParams:
    gain: float = spec_field(1.0, range=(0.0, 16.0), doc="base exposure multiplier")
    gain_sigma_stops: float = spec_field(0.1, range=(0.0, 4.0), doc="std of the per-view log2 gain")
    wb_sigma: float = spec_field(0.02, range=(0.0, 1.0), doc="std of the per-view, per-channel natural-log gain")


@register_effect("exposure", ExposureParams)
def exposure(image: np.ndarray, params: ExposureParams, ctx: EffectContext, rng: np.random.Generator) -> np.ndarray:
    """Per-view exposure gain (log-normal, in stops) and white-balance jitter, then sensor saturation at 1."""
    g = params.gain * 2.0 ** rng.normal(scale=params.gain_sigma_stops)
    wb = np.exp(rng.normal(scale=params.wb_sigma, size=3))
    return np.clip(image * (g * wb).astype(np.float32), 0.0, 1.0)


@dataclass(frozen=True)
class VignettingParams:
    strength: float = spec_field(0.3, range=(0.0, 1.0), doc="relative darkening at the image corners")


@register_effect("vignetting", VignettingParams)
def vignetting(image: np.ndarray, params: VignettingParams, ctx: EffectContext, rng: np.random.Generator) -> np.ndarray:
    """Radial falloff 1 - strength * (r / r_corner)^2 about the principal point."""
    h, w = image.shape[:2]
    cx, cy = ctx.K[0, 2], ctx.K[1, 2]
    u = np.arange(w) + 0.5 - cx  # pixel centres, our convention
    v = np.arange(h) + 0.5 - cy
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    corner2 = max((x - cx) ** 2 + (y - cy) ** 2 for x in (0, w) for y in (0, h))
    gain = (1.0 - params.strength * r2 / corner2).astype(np.float32)
    return image * gain[..., None]
