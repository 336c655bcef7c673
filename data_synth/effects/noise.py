"""Sensor noise effects: additive Gaussian and signal-dependent Poisson-Gaussian."""

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
