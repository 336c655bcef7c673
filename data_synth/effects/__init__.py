"""Degradation effects, registered by name (see `registry`). Importing this package registers them all."""

from data_synth.effects import blur, codec, noise, photometric  # noqa: F401  (registration)
from data_synth.effects.registry import (
    EFFECTS,
    EffectContext,
    EffectDef,
    apply_effects,
    effect_rng,
    effect_table,
    effects_need,
    parse_effect,
    register_effect,
)

__all__ = [
    "EFFECTS",
    "EffectContext",
    "EffectDef",
    "apply_effects",
    "effect_rng",
    "effect_table",
    "effects_need",
    "parse_effect",
    "register_effect",
]
