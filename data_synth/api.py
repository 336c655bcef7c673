"""The functional entry point: scene name/path -> dataset folder."""

from __future__ import annotations

from pathlib import Path

from data_synth.dataset import write_dataset
from data_synth.scene_file import load_scene


def render_scene(scene: str | Path, out: str | Path, *, seed: int | None = None,
                 size_wh: tuple[int, int] | None = None, views: int | None = None,
                 overwrite: bool = False) -> Path:
    """Render a built-in or user scene into a dataset folder.

    Args:
        scene: built-in name (`data_synth.builtin_scenes()`) or a .toml path.
        out: output folder (written atomically when complete): new, empty, or, with `overwrite`,
            a dataset rendered before; anything else is refused (`mvgeo.common.output`).
        seed: overrides the scene's seed (the effects' random streams).
        size_wh: overrides the image size (W, H); the field of view is kept.
        views: overrides the number of views (not for explicit pose lists).
        overwrite: replace a dataset rendered before at `out`.

    Returns:
        The output folder.

    Example:
        >>> from data_synth import render_scene
        >>> render_scene("llff_like", Path("/tmp/llff"), size_wh=(128, 96), views=4)  # doctest: +SKIP
    """
    spec = load_scene(scene, seed=seed, size_wh=size_wh, views=views)
    return write_dataset(spec, Path(out), overwrite=overwrite)
