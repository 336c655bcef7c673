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
  The noise is correlated between neighbouring pixels, as a camera's raw-to-RGB
  step leaves it (each channel from its own sites: the channels' noises stay
  independent); the image itself keeps its detail.
- ``jpeg:Q``: a round trip through an 8-bit JPEG at libjpeg quality Q (4:2:0
  chroma, OpenCV's encoder; `data_synth.effects.codec.jpeg`), as a camera or a
  phone stores its photos.
- ``A+B``: A, then B on its result, e.g. ``bayer-pg:0.01,5+jpeg:90`` (the noisy
  photo as a camera writes it to a JPEG). Each step appears at most once.

Noise is added to the (resized, quantised) clean image in [0, 1] float,
clipped to [0, 1] (a file holds nothing else; a sensor saturates too) and
quantised to the output's bit depth (8-bit: rounding adds a uniform error of
variance 1/12 on the 0..255 scale, 0.003 % of sigma^2 at sigma = 25). Where the
clean value is near 0 or 1 the difference `images - clean` is therefore a
clipped Gaussian: on templeSparseRing's black background at sigma = 25 the
whole images give std 19.2 and mean +6.1 (0..255 scale), pixels with clean
values in [0.4, 0.6] give std 25.01 and mean +0.02.
Step k's random stream on view i is ``default_rng([seed, crc32(view name), k])``
(`data_synth.effects.effect_rng`): adding or dropping a view does not change
another view's noise, and ``N+jpeg:Q`` compresses exactly the noise that ``N``
alone draws.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mvgeo.common.errors import InputError

__all__ = ["Degradation", "DegradationStep", "parse_noise"]

_FIX = "write none, gaussian:SIGMA_8BIT (e.g. gaussian:25), poisson-gaussian:GAIN,READ_SIGMA_8BIT " \
       "(e.g. poisson-gaussian:0.01,5), bayer-pg:GAIN,READ_SIGMA_8BIT (e.g. bayer-pg:0.01,5) or jpeg:QUALITY, " \
       "or several joined by + (e.g. bayer-pg:0.01,5+jpeg:90)"

_FORMULAS = {
    "gaussian": "y = clip(x + N(0, (sigma_8bit/255)^2)), x in [0, 1]",
    "poisson_gaussian": "y = clip(gain * Poisson(x / gain) + N(0, (read_sigma_8bit/255)^2)), "
                        "Var[y|x] = gain x + (read_sigma_8bit/255)^2",
    "bayer_noise": "y = clip(x + D(n)), n = gain * Poisson(m / gain) - m + N(0, (read_sigma_8bit/255)^2) on the "
                   "RGGB mosaic m of x, D = bilinear demosaicing",
    "jpeg": "y = decode(encode_jpeg(round(255 x), quality)) / 255, libjpeg via OpenCV, 4:2:0 chroma",
}


@dataclass(frozen=True)
class DegradationStep:
    """One step of a `--noise` spec.

    Attributes:
        effect: the `data_synth` effect name ("gaussian", "poisson_gaussian", "bayer_noise", "jpeg").
        params: the effect's parameters, as `data_synth` names them (e.g. {"sigma_8bit": 25.0}).
    """

    effect: str
    params: dict[str, float]

    def meta(self) -> dict[str, Any]:
        return {"model": self.effect, "params": dict(self.params), "formula": _FORMULAS[self.effect]}


@dataclass(frozen=True)
class Degradation:
    """A parsed `--noise` spec: its steps, applied in order.

    Attributes:
        spec: the text as given (normalised: lower case, no spaces).
        steps: the degradations in the order they are applied; empty for none.
    """

    spec: str
    steps: tuple[DegradationStep, ...] = ()

    @property
    def is_none(self) -> bool:
        return not self.steps

    @property
    def effect(self) -> str | None:
        """The first step's effect name (the noise model of a ``NOISE+jpeg:Q`` spec); None for none."""
        return self.steps[0].effect if self.steps else None

    @property
    def params(self) -> dict[str, float]:
        """The first step's parameters ({} for none)."""
        return dict(self.steps[0].params) if self.steps else {}

    def meta(self, seed: int) -> dict[str, Any] | None:
        """What meta.json records: the steps (model, parameters, formula), the spec and the seed; a
        one-step spec also has its step's keys at the top level."""
        if not self.steps:
            return None
        stream = "numpy default_rng([seed, crc32(view name), k]) per view, k the step's index"
        out = {"spec": self.spec, "steps": [st.meta() for st in self.steps], "seed": int(seed), "stream": stream}
        if len(self.steps) == 1:
            out = {**self.steps[0].meta(), **out}
        return out

    def apply(self, image: np.ndarray, *, seed: int, view_name: str, K: np.ndarray) -> np.ndarray:
        """The degraded copy of `image` ((H, W, 3) float32 in [0, 1]); unchanged copy for no noise."""
        if not self.steps:
            return np.array(image, dtype=np.float32, copy=True)
        from data_synth.effects import EffectContext, apply_effects, parse_effect

        specs = tuple(parse_effect({"type": st.effect, **st.params}, key="--noise", path=None) for st in self.steps)
        return apply_effects(image, specs, seed=seed, ctx=EffectContext(view_name=view_name, K=K))


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
        InputError: unknown model, wrong count of numbers, a value out of range, or a step given twice.
    """
    spec = "none" if text is None else "".join(str(text).split()).lower()
    if spec in ("none", ""):
        return Degradation("none")
    steps = tuple(_parse_step(part, spec) for part in spec.split("+"))
    effects = [st.effect for st in steps]
    if len(set(effects)) != len(effects):
        raise InputError(f"--noise {spec!r} gives the same step twice", fix=_FIX)
    return Degradation(spec, steps)


def _parse_step(part: str, spec: str) -> DegradationStep:
    kind, _, args = part.partition(":")
    if kind == "gaussian":
        (sigma,) = _numbers(args, 1, spec)
        step = DegradationStep("gaussian", {"sigma_8bit": sigma})
    elif kind in ("poisson-gaussian", "poisson_gaussian"):
        gain, read = _numbers(args, 2, spec)
        step = DegradationStep("poisson_gaussian", {"gain": gain, "read_sigma_8bit": read})
    elif kind in ("bayer-pg", "bayer_pg"):
        gain, read = _numbers(args, 2, spec)
        step = DegradationStep("bayer_noise", {"gain": gain, "read_sigma_8bit": read})
    elif kind == "jpeg":
        (quality,) = _numbers(args, 1, spec)
        if quality != int(quality):
            raise InputError(f"--noise {spec!r}: the JPEG quality is a whole number from 1 to 100", fix=_FIX)
        step = DegradationStep("jpeg", {"quality": int(quality)})
    else:
        what = "an empty step" if not part else f"unknown noise model {kind!r}"
        raise InputError(f"{what} in --noise {spec!r}", fix=_FIX)
    from data_synth.effects import parse_effect

    parse_effect({"type": step.effect, **step.params}, key="--noise", path=None)  # range checks, ConfigError
    return step
