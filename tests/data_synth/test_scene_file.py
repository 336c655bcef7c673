"""Scene files: built-ins, inheritance, round trips and errors that name the key."""

from __future__ import annotations

import tomllib

import pytest

from data_synth import builtin_scenes, load_scene, parse_scene, rig_views
from data_synth.scene_file import scene_to_toml
from data_synth.toml_writer import dumps
from mvgeo.common.errors import ConfigError, InputError
from tests.data_synth.conftest import TINY_SCENE, write_scene

BUILTINS = ["llff_like", "llff_like_clean", "object_ring", "poisson", "hard_lowtexture", "hard_repetitive",
            "hard_tinybaseline", "hard_highnoise"]


def test_all_builtins_exist_and_resolve():
    assert set(BUILTINS) <= set(builtin_scenes())
    for name in BUILTINS:
        spec = load_scene(name)
        assert spec.info.name == name
        assert spec.render.size == (504, 378)
        # The resolved TOML parses back to an identical spec (inheritance flattened, defaults filled).
        assert scene_to_toml(parse_scene(tomllib.loads(scene_to_toml(spec)))) == scene_to_toml(spec)


def test_builtin_contents_match_the_issue():
    assert [(e.type, e.params.sigma01) for e in load_scene("llff_like").effects] == [("gaussian", 25 / 255)]
    assert load_scene("llff_like_clean").effects == ()
    assert [(e.type, e.params.sigma01) for e in load_scene("hard_highnoise").effects] == [("gaussian", 50 / 255)]
    assert load_scene("poisson").effects[0].type == "poisson_gaussian"
    ring = load_scene("object_ring")
    assert ring.rig.type == "ring" and ring.rig.num_views == 24
    llff = load_scene("llff_like")
    assert llff.rig.type == "forward" and llff.rig.num_views == 20
    assert load_scene("hard_tinybaseline").rig.extent[0] == pytest.approx(llff.rig.extent[0] / 10)


def test_llff_baselines_and_rotations_are_handheld_like():
    import numpy as np

    from data_synth import rig_views

    views = rig_views(load_scene("llff_like").rig)
    centres = np.array([-v.cam_from_world[:, :3].T @ v.cam_from_world[:, 3] for v in views])
    axes = np.array([v.cam_from_world[2, :3] for v in views])
    span = np.max(np.linalg.norm(centres[:, None] - centres[None], axis=2))
    scene_depth = 4.0  # distance to the look-at point; objects lie between 2 and 7.5 m
    assert 0.05 <= span / scene_depth <= 0.2
    angles = np.degrees(np.arccos(np.clip(axes @ axes.mean(0) / np.linalg.norm(axes.mean(0)), -1, 1)))
    assert 0.5 < angles.max() < 8.0  # a few degrees of rotation


def test_overrides(tmp_path):
    spec = load_scene("llff_like", seed=9, size_wh=(100, 80), views=5)
    assert spec.info.seed == 9 and spec.render.size == (100, 80) and spec.rig.views == 5
    with pytest.raises(ConfigError) as info:
        load_scene(write_scene(tmp_path, TINY_SCENE), views=4)  # a list rig has explicit poses
    assert info.value.key == "rig.views"
    with pytest.raises(ConfigError) as info:
        load_scene("llff_like", size_wh=(4, 4))
    assert info.value.key == "render.size[0]"


def test_inheritance_from_a_relative_file(tmp_path):
    write_scene(tmp_path, TINY_SCENE, "parent.toml")
    child = write_scene(tmp_path, 'base = "parent.toml"\n[render]\nsupersample = 3\n', "child.toml")
    spec = load_scene(child)
    assert spec.render.supersample == 3 and spec.render.size == (64, 48)  # merged key by key
    loop = write_scene(tmp_path, 'base = "loop.toml"\n', "loop.toml")
    with pytest.raises(ConfigError, match="too deep"):
        load_scene(loop)


@pytest.mark.parametrize(("edit", "key", "expected"), [
    (("[render]\nsize = [64, 48]", "[render]\nsize = [64, 48]\nsupersampel = 2"), "render.supersampel", "one of"),
    (("supersample = 2", 'supersample = "two"'), "render.supersample", "an integer"),
    (("supersample = 2", "supersample = 0"), "render.supersample", "[1, 8]"),
    (("fov_x_deg = 60.0", "fov_x_deg = 200.0"), "camera.fov_x_deg", "[1, 170]"),
    (('radius = 0.4', 'radius = -0.4'), "objects[2].radius", "[1e-06, inf]"),
    (('radius = 0.4', 'radius = 0.4\nsize = [1.0, 1.0, 1.0]'), "objects[2].size", "does not apply"),
    (('texture = "c"\n', 'texture = "nope"\n'), "objects[1].texture", "one of c, t"),
    (('shape = "sphere"', 'shape = "torus"'), "objects[2].shape", "one of plane"),
    (('pattern = "checker"', 'pattern = "checkers"'), "textures.c.pattern", "one of"),
    (('colors = [[0.1, 0.1, 0.1], [0.9, 0.9, 0.9]]', 'colors = [[0.1, 0.1], [0.9, 0.9, 0.9]]'),
     "textures.c.colors[0]", "3 entries"),
    (('[rig]\ntype = "list"', '[rig]\ntype = "list"\nradius = 3.0'), "rig.radius", "does not apply"),
    (('look_at = [-0.1, 4.0, 0.7]', 'look_at = [-0.25, -0.2, 0.9]'), "rig.poses[2].look_at", "different"),
    (('look_at = [-0.1, 4.0, 0.7]', 'look_at = [-0.25, -0.2, 5.0]'), "rig.poses", "parallel to the viewing"),
    (('seed = 3', 'seed = -3'), "scene.seed", "[0, 4.29497e+09]"),
    (('[scene]', '[scen]\nx = 1\n[scene]'), "scen", "one of base"),
])
def test_bad_scene_files_name_file_key_and_expectation(tmp_path, edit, key, expected):
    old, new = edit
    assert old in TINY_SCENE
    path = write_scene(tmp_path, TINY_SCENE.replace(old, new, 1))
    with pytest.raises(ConfigError) as info:
        load_scene(path)
    err = info.value
    assert err.key.startswith(key)
    assert str(path) in str(err)
    if expected is not None:
        assert expected in str(err)


def test_duplicate_key_toml_and_missing_files(tmp_path):
    with pytest.raises(InputError, match="not valid TOML"):
        load_scene(write_scene(tmp_path, TINY_SCENE + "\n[render]\nsize = [1, 2]\n"))
    with pytest.raises(InputError, match="no built-in scene"):
        load_scene("no_such_scene")
    with pytest.raises(ConfigError) as info:
        load_scene(write_scene(tmp_path, "[scene]\nname = 'x'\n", "empty.toml"))
    assert info.value.key == "textures"


def test_a_file_that_is_not_utf8_text_is_an_input_error(tmp_path):
    """A non-UTF-8 .toml, or an image passed as the scene, names the file instead of a UnicodeDecodeError."""
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes(TINY_SCENE.replace("[scene]", "# caf\xe9\n[scene]", 1).encode("latin-1"))
    png = tmp_path / "photo.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    for path in (latin1, png):
        with pytest.raises(InputError, match="not a UTF-8 text file") as info:
            load_scene(path)
        assert str(path) in str(info.value) and "fix:" in str(info.value)
    child = write_scene(tmp_path, 'base = "latin1.toml"\n', "child.toml")
    with pytest.raises(InputError, match="not a UTF-8 text file") as info:
        load_scene(child)
    assert str(latin1) in str(info.value)


def test_toml_writer_round_trip():
    data = {"a": 1, "b": 1.5e-7, "c": "q\"uote", "d": [1, 2], "e": [[0.1, 0.2], [0.3, 0.4]], "f": True,
            "t": {"x": 0.1, "sub": {"y": "z"}}, "arr": [{"k": 1}, {"k": 2, "n": {"m": 3}}], "empty": []}
    assert tomllib.loads(dumps(data)) == data


def test_inheriting_scene_may_change_the_rig_type(tmp_path):
    # The base's forward-only rig keys (extent, pattern, ...) are not carried into a ring rig; the keys a
    # ring takes (up, seed, jitter) still are, and the child's own keys win.
    child = write_scene(tmp_path, 'base = "llff_like"\n[rig]\ntype = "ring"\nradius = 2.0\n'
                                  'look_at = [0.0, 3.0, 0.5]\n', "ring.toml")
    spec = load_scene(child)
    llff = load_scene("llff_like")
    assert spec.rig.type == "ring" and spec.rig.radius == 2.0 and spec.rig.look_at == (0.0, 3.0, 0.5)
    assert spec.rig.views == llff.rig.views and spec.rig.position_jitter == llff.rig.position_jitter
    assert len(rig_views(spec.rig)) == llff.rig.views
    # A key that does not apply to the child's own rig type is still refused, naming it.
    bad = write_scene(tmp_path, 'base = "llff_like"\n[rig]\ntype = "ring"\nextent = [0.1, 0.1]\n', "bad.toml")
    with pytest.raises(ConfigError) as info:
        load_scene(bad)
    assert info.value.key == "rig.extent"
