"""data_synth: synthetic scenes with known poses that simulate only the effects a scene calls for.

Layers: `noise` (kernel) -> `textures`, `geometry`, `intrinsics`, `rigs`,
`render`, `effects` (functional) -> `SceneRenderer` (thin class) ->
`dataset.write_dataset` / `api.render_scene` -> `cli` (`data-synth`).
Scene files are TOML, validated by `scene_file` against `spec`.
"""

from data_synth.api import render_scene
from data_synth.dataset import write_dataset
from data_synth.effects import EFFECTS
from data_synth.render import SceneRenderer, ViewRender
from data_synth.rigs import View, rig_views, split_views
from data_synth.scene_file import builtin_scenes, load_scene, parse_scene, scene_to_toml
from data_synth.spec import SceneSpec

__all__ = [
    "EFFECTS",
    "SceneRenderer",
    "SceneSpec",
    "View",
    "ViewRender",
    "builtin_scenes",
    "load_scene",
    "parse_scene",
    "render_scene",
    "rig_views",
    "scene_to_toml",
    "split_views",
    "write_dataset",
]
