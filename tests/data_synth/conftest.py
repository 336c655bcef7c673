"""Small scenes for data_synth tests (tiny images so the whole module runs in seconds)."""

from __future__ import annotations

from pathlib import Path

import pytest

TINY_SCENE = """
[scene]
name = "tiny"
seed = 3

[render]
size = [64, 48]
supersample = 2
outputs = ["depth", "alpha", "normals"]

[camera]
fov_x_deg = 60.0

[rig]
type = "list"

[[rig.poses]]
position = [0.0, 0.0, 1.0]
look_at = [0.0, 4.0, 0.6]

[[rig.poses]]
position = [0.3, 0.1, 1.1]
look_at = [0.1, 4.0, 0.6]

[[rig.poses]]
position = [-0.25, -0.2, 0.9]
look_at = [-0.1, 4.0, 0.7]
roll_deg = 4.0

[textures.t]
pattern = "noise"
colors = [[0.1, 0.2, 0.3], [0.9, 0.8, 0.6]]
scale = 0.3
detail = 0.3
detail_scale = 0.05

[textures.c]
pattern = "checker"
colors = [[0.1, 0.1, 0.1], [0.9, 0.9, 0.9]]
scale = 0.2

[[objects]]
name = "wall"
shape = "plane"
size = [12.0, 6.0]
rotate_deg = [90.0, 0.0, 0.0]
translate = [0.0, 6.0, 3.0]
texture = "t"

[[objects]]
name = "ground"
shape = "plane"
size = [12.0, 12.0]
translate = [0.0, 4.0, 0.0]
texture = "c"

[[objects]]
name = "ball"
shape = "sphere"
radius = 0.4
translate = [0.2, 3.0, 0.5]
texture = "t"

[[objects]]
name = "box"
shape = "box"
size = [0.5, 0.4, 0.6]
rotate_deg = [0.0, 0.0, 30.0]
translate = [-0.8, 3.5, 0.3]
texture = "c"
"""


@pytest.fixture
def tiny_scene_file(tmp_path: Path) -> Path:
    """A 64x48 scene with three explicit poses, all outputs, no effects."""
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_SCENE)
    return path


def write_scene(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path
