"""Declared degradations for imported photographs: exactly the noise the user asks for.

The noise itself is `data_synth`'s (`data_synth.effects.noise`): the same
models, parameter checks and per-view random streams as synthetic scenes.

Spec strings (`--noise`):

- ``none``: no degradation; `images/` files are byte-identical to `clean/`.
- ``gaussian:S``: ``y = clip(x + N(0, (S/255)^2))``, S the standard deviation
  on the 0..255 scale (``gaussian:25`` is sigma = 25/255).
- ``poisson-gaussian:A,S``: ``y = clip(A Poisson(x / A) + N(0, (S/255)^2))``,
  so ``Var[y | x] = A x + (S/255)^2`` on the [0, 1] scale (A: the shot-noise
  gain, 1 / full-well electrons; S: the read noise on the 0..255 scale).
- ``bayer-pg:A,S``: the same noise on the RGGB Bayer mosaic of the photo, then
  bilinear demosaicing: ``y = clip(x + D(n))`` (`data_synth.effects.noise.bayer_noise`).
  The noise is correlated between neighbouring pixels and between channels, as a
  camera's raw-to-RGB step leaves it; the image itself keeps its detail.

Noise is added to the (resized, quantised) clean image in [0, 1] float,
clipped to [0, 1] (a file holds nothing else; a sensor saturates too) and
quantised to the output's bit depth (8-bit: rounding adds a uniform error of
variance 1/12 on the 0..255 scale, 0.003 % of sigma^2 at sigma = 25). Where the
clean value is near 0 or 1 the difference `images - clean` is therefore a
clipped Gaussian: on templeSparseRing's black background at sigma = 25 the
whole images give std 19.2 and mean +6.1 (0..255 scale), pixels with clean
values in [0.4, 0.6] give std 25.01 and mean +0.02.
View i's stream is ``default_rng([seed, crc32(view name), 0])``
(`data_synth.effects.effect_rng`): adding or dropping a view does not change
another view's noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mvgeo.common.errors import InputError

__all__ = ["Degradation", "parse_noise"]

_FIX = "write none, gaussian:SIGMA_8BIT (e.g. gaussian:25), poisson-gaussian:GAIN,READ_SIGMA_8BIT " \
       "(e.g. poisson-gaussian:0.01,5) or bayer-pg:GAIN,READ_SIGMA_8BIT (e.g. bayer-pg:0.01,5)"


@dataclass(frozen=True)
class Degradation:
    """A parsed `--noise` spec.

    Attributes:
        spec: the text as given (normalised: lower case, no spaces).
        effect: the `data_synth` effect name ("gaussian", "poisson_gaussian", "bayer_noise"), None for no noise.
        params: the effect's parameters, as `data_synth` names them (e.g. {"sigma_8bit": 25.0}).
    """

    spec: str
    effect: str | None
    params: dict[str, float]

    @property
    def is_none(self) -> bool:
        return self.effect is None

    def meta(self, seed: int) -> dict[str, Any] | None:
        """What meta.json records: the model, its parameters and formula, and the seed."""
        if self.effect is None:
            return None
        formula = {"gaussian": "y = clip(x + N(0, (sigma_8bit/255)^2)), x in [0, 1]",
                   "poisson_gaussian": "y = clip(gain * Poisson(x / gain) + N(0, (read_sigma_8bit/255)^2)), "
                                       "Var[y|x] = gain x + (read_sigma_8bit/255)^2",
                   "bayer_noise": "y = clip(x + D(n)), n = gain * Poisson(m / gain) - m "
                                  "+ N(0, (read_sigma_8bit/255)^2) on the RGGB mosaic m of x, "
                                  "D = bilinear demosaicing"}[self.effect]
        return {"model": self.effect, "spec": self.spec, "params": dict(self.params), "formula": formula,
                "seed": int(seed), "stream": "numpy default_rng([seed, crc32(view name), 0]) per view"}

    def apply(self, image: np.ndarray, *, seed: int, view_name: str, K: np.ndarray) -> np.ndarray:
        """The degraded copy of `image` ((H, W, 3) float32 in [0, 1]); unchanged copy for no noise."""
        if self.effect is None:
            return np.array(image, dtype=np.float32, copy=True)
        from data_synth.effects import EffectContext, apply_effects, parse_effect

        spec = parse_effect({"type": self.effect, **self.params}, key="--noise", path=None)
        return apply_effects(image, (spec,), seed=seed, ctx=EffectContext(view_name=view_name, K=K))


def _numbers(text: str, count: int, spec: str) -> list[float]:
    parts = [p for p in text.split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) != count or not all(np.isfinite(vals)):
        raise InputError(f"--noise {spec!r}: expected {count} number{'s' if count > 1 else ''} after the colon",
                         fix=_FIX)
    return vals


def parse_noise(text: str | None) -> Degradation:
    """Parse a `--noise` spec (see the module docstring); None means no noise.

    The parameters are checked by `data_synth`'s effect schema (ranges), so a bad value fails here,
    before any image is read.

    Raises:
        InputError: unknown model, wrong count of numbers, or a value out of range.
    """
    spec = "none" if text is None else "".join(str(text).split()).lower()
    kind, _, args = spec.partition(":")
    if kind in ("none", "") and not args:
        return Degradation("none", None, {})
    if kind == "gaussian":
        (sigma,) = _numbers(args, 1, spec)
        deg = Degradation(spec, "gaussian", {"sigma_8bit": sigma})
    elif kind in ("poisson-gaussian", "poisson_gaussian"):
        gain, read = _numbers(args, 2, spec)
        deg = Degradation(spec, "poisson_gaussian", {"gain": gain, "read_sigma_8bit": read})
    elif kind in ("bayer-pg", "bayer_pg"):
        gain, read = _numbers(args, 2, spec)
        deg = Degradation(spec, "bayer_noise", {"gain": gain, "read_sigma_8bit": read})
    else:
        raise InputError(f"unknown noise model {kind!r} in --noise {spec!r}", fix=_FIX)
    from data_synth.effects import parse_effect

    parse_effect({"type": deg.effect, **deg.params}, key="--noise", path=None)  # range checks, ConfigError
    return deg
