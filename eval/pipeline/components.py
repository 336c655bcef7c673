"""The pipeline's only doorway to the four component packages.

`denoise`, `mvgeo.align`, `splat` and `data_synth` are imported lazily, by
name, so that the framework (and its tests) work while a component is still
being written; a stage that needs a missing piece raises
`MissingComponentError` naming it. The names the pipeline relies on are
listed here, in one place:

- denoise (by submodule): `n2v.train_n2v(images, config, *, seed, device)`, `n2v.N2V_PRESETS`,
  `inference.denoise_images(model, images, *, passes, seed)`,
  `round2.finetune_round2(model, noisy_images, renders, config, *, seed)`, `round2.Round2Config`
  (no preset table: "default" is `Round2Config()`), `view_selection.select_views(cfw, images, k, *, seed)`,
  `model.save_checkpoint(path, model)`, `model.load_checkpoint(path, *, device)`;
- mvgeo.align: `align_images(image_paths, config) -> AlignResult`, `write_align_result(out, result)`,
  `AlignConfig` (preset "default") and `PREVIEW` (preset "preview");
- splat (by submodule): `train.train_gaussians(images, cameras, cfw, xyz, rgb, config, *, device)`,
  `train.TRAIN_PRESETS`, `render.render_views(model, cameras, cfw)`, `pose_fit.fit_pose(...)`,
  `ply.write_gaussian_ply(path, model)`, `ply.read_gaussian_ply(path, *, device)`;
- data_synth: `render_scene(scene, out, *, seed, size_wh, views) -> Path`.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Mapping

from mvgeo.common.errors import DgsError

__all__ = ["MissingComponentError", "component_config", "require"]


class MissingComponentError(DgsError):
    """A pipeline stage needs a function or config of a component that is not available."""


def require(module: str, attr: str, *, needed_for: str):
    """`module.attr`, imported on first use.

    Raises:
        MissingComponentError: the module cannot be imported or lacks `attr`.
    """
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        raise MissingComponentError(f"{needed_for} needs `{module}.{attr}`, but `{module}` cannot be "
                                    f"imported ({exc})") from exc
    obj = getattr(mod, attr, None)
    if obj is None:
        raise MissingComponentError(f"{needed_for} needs `{module}.{attr}`, which `{module}` does not "
                                    f"provide (yet)")
    return obj


def component_config(module: str, presets_attr: str, preset: str, overrides: Mapping[str, object], *,
                     needed_for: str, config_cls: str | None = None):
    """A component's config: its named preset with the non-None `overrides` fields replaced.

    Args:
        module, presets_attr: where the `name -> config` table lives.
        preset: the preset name.
        overrides: field -> value; None values are ignored.
        needed_for: what needs it (for the error message).
        config_cls: for components without a presets table: the config class
            in `module`, whose defaults are the preset "default".

    Raises:
        MissingComponentError: the presets table, the preset name or an overridden field is missing.
    """
    if config_cls is not None:
        if preset != "default":
            raise MissingComponentError(f"{needed_for}: `{module}` has no presets table, only the defaults of "
                                        f"`{config_cls}` (preset 'default'); got preset {preset!r}")
        table = {"default": require(module, config_cls, needed_for=needed_for)()}
    else:
        table = require(module, presets_attr, needed_for=needed_for)
    if preset not in table:
        raise MissingComponentError(f"{needed_for}: `{module}.{presets_attr}` has no preset {preset!r} "
                                    f"(has {', '.join(map(str, table))})")
    cfg = table[preset]
    changes = {k: v for k, v in overrides.items() if v is not None}
    names = {f.name for f in dataclasses.fields(cfg)}
    unknown = sorted(set(changes) - names)
    if unknown:
        raise MissingComponentError(f"{needed_for}: {type(cfg).__name__} has no field(s) {unknown}")
    return dataclasses.replace(cfg, **changes)
