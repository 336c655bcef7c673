"""The effect registry: degradations registered by name with declared, validated parameters.

An effect is a pure function `fn(image, params, ctx, rng) -> image` on a
(H, W, 3) float32 image in [0, 1] (values may leave [0, 1] in between; the
dataset writer clips when it quantises). `params` is the effect's frozen
params dataclass (validated by `data_synth.schema`), `ctx` carries what
the effect may read about the view, and `rng` is the effect's own stream,
`numpy.random.default_rng([scene seed, crc32(view name), effect index])`,
so adding a view or an effect does not change any other view's or effect's noise.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from data_synth.schema import from_table, join_key, to_table
from data_synth.spec import EffectSpec
from mvgeo.common.errors import ConfigError


@dataclass(frozen=True)
class EffectContext:
    """What an effect may know about the view it degrades.

    Attributes:
        view_name: the view's name.
        K: (3, 3) float64 pinhole matrix (our pixel convention).
        depth: (H, W) float32 z-depth (inf on a miss), present only when the
            effect declared that it needs depth.
    """

    view_name: str
    K: np.ndarray
    depth: np.ndarray | None = None


EffectFn = Callable[[np.ndarray, Any, EffectContext, np.random.Generator], np.ndarray]


@dataclass(frozen=True)
class EffectDef:
    """A registered effect.

    Attributes:
        name: the `type` used in scene files.
        params_cls: frozen dataclass of its parameters (spec_field metadata).
        fn: the effect.
        needs: params -> set of render outputs the effect reads ({"depth"} or empty).
        summary: one line for docs and `data-synth effects`.
    """

    name: str
    params_cls: type
    fn: EffectFn
    needs: Callable[[Any], frozenset[str]]
    summary: str


EFFECTS: dict[str, EffectDef] = {}


def register_effect(name: str, params_cls: type, *, needs: Callable[[Any], frozenset[str]] | None = None):
    """Decorator registering `fn` as effect `name` (summary: the first docstring line)."""

    def deco(fn: EffectFn) -> EffectFn:
        if name in EFFECTS:
            raise RuntimeError(f"effect {name!r} registered twice")
        summary = (fn.__doc__ or "").strip().splitlines()[0] if fn.__doc__ else ""
        EFFECTS[name] = EffectDef(name, params_cls, fn, needs or (lambda p: frozenset()), summary)
        return fn

    return deco


def parse_effect(table: Mapping[str, Any], *, key: str, path: Path | None) -> EffectSpec:
    """Validate one `[[effects]]` table: `type` plus that effect's parameters."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"got {table!r}", key=key, path=path, expected="a table with a `type` key")
    if "type" not in table:
        raise ConfigError("missing required key", key=join_key(key, "type"), path=path,
                          expected="one of " + ", ".join(sorted(EFFECTS)))
    name = table["type"]
    if not isinstance(name, str) or name not in EFFECTS:
        raise ConfigError(f"unknown effect {name!r}", key=join_key(key, "type"), path=path,
                          expected="one of " + ", ".join(sorted(EFFECTS)))
    params = from_table(EFFECTS[name].params_cls, {k: v for k, v in table.items() if k != "type"},
                        key=key, path=path)
    return EffectSpec(type=name, params=params)


def effect_table(effect: EffectSpec) -> dict[str, Any]:
    """The TOML table of an effect (inverse of `parse_effect`)."""
    return {"type": effect.type, **to_table(effect.params)}


def effects_need(effects: tuple[EffectSpec, ...]) -> frozenset[str]:
    """Union of the render outputs the listed effects read."""
    out: frozenset[str] = frozenset()
    for e in effects:
        out |= EFFECTS[e.type].needs(e.params)
    return out


def effect_rng(seed: int, view_name: str, effect_index: int) -> np.random.Generator:
    """The random stream of effect number `effect_index` (in scene order) on view `view_name`."""
    return np.random.default_rng([int(seed), zlib.crc32(view_name.encode("utf-8")), int(effect_index)])


def apply_effects(image: np.ndarray, effects: tuple[EffectSpec, ...], *, seed: int, ctx: EffectContext) -> np.ndarray:
    """Apply `effects` in order to a copy of `image` ((H, W, 3) float32); the input is never modified."""
    out = np.array(image, dtype=np.float32, copy=True)
    for i, e in enumerate(effects):
        d = EFFECTS[e.type]
        if "depth" in d.needs(e.params) and ctx.depth is None:
            raise RuntimeError(f"effect {e.type} needs depth but none was rendered")  # a bug in the caller
        out = np.asarray(d.fn(out, e.params, ctx, effect_rng(seed, ctx.view_name, i)), dtype=np.float32)
    return out
