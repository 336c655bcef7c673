"""Scene files: find built-ins, read TOML, resolve `base` inheritance, validate, override, write back.

`load_scene("llff_like")` or `load_scene("path/to/scene.toml")` returns a
validated `SceneSpec`; `scene_to_toml(spec)` writes the resolved scene
(inheritance flattened, defaults filled in, seed included) so a dataset's
`scene.toml` re-renders the same dataset.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from data_synth.effects import effect_table, parse_effect
from data_synth.schema import from_table, join_key, to_table
from data_synth.spec import (
    RIG_KEYS,
    CameraSpec,
    LightingSpec,
    ObjectSpec,
    RenderSpec,
    RigSpec,
    SceneInfo,
    SceneSpec,
    SplitSpec,
    TextureSpec,
)
from data_synth.toml_writer import dumps
from mvgeo.common.errors import ConfigError, DegenerateGeometryError, InputError

_ROOT_KEYS = ("base", "scene", "render", "lighting", "camera", "rig", "split", "textures", "objects", "effects")
_MAX_BASE_DEPTH = 8


def builtin_dir() -> Path:
    """The folder of built-in scene files (package data `data_synth/scenes/*.toml`)."""
    return Path(str(resources.files("data_synth") / "scenes"))


def builtin_scenes() -> dict[str, Path]:
    """Built-in scene name -> file, sorted by name."""
    return {p.stem: p for p in sorted(builtin_dir().glob("*.toml"))}


def find_scene(scene: str | Path) -> Path:
    """A built-in name or a path -> the scene file.

    Raises:
        InputError: neither a built-in name nor an existing file.
    """
    text = str(scene)
    builtins = builtin_scenes()
    if text in builtins:
        return builtins[text]
    path = Path(scene)
    if path.is_file():
        return path
    raise InputError(f"no built-in scene or scene file named {text!r}", path=path if path.suffix else None,
                     fix="run `data-synth list` for built-in scenes, or pass a path to a .toml scene file")


def read_toml(path: Path) -> dict[str, Any]:
    """Parse a TOML file.

    Raises:
        InputError: the file cannot be read, is not UTF-8 text (e.g. an image passed as the scene), or is
            not valid TOML; the message names the file.
    """
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", path=path, fix="fix the syntax at the position given") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"not a UTF-8 text file (byte {exc.start} cannot be decoded), so not a TOML scene file",
                         path=path, fix="pass a .toml scene file saved as UTF-8 (`data-synth list` shows the "
                         "built-in scenes)") from exc
    except OSError as exc:
        raise InputError(f"cannot read scene file: {exc.strerror}", path=path,
                         fix="make the file readable (its permissions), or pass another scene file") from exc


def merge_tables(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Deep merge: tables merged key by key, everything else (arrays included) replaced."""
    out = dict(base)
    for k, v in override.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = merge_tables(out[k], v)
        else:
            out[k] = v
    return out


def resolve_inheritance(path: Path, *, _depth: int = 0) -> dict[str, Any]:
    """The scene file's table with `base` scenes merged in (the file's own keys win)."""
    data = read_toml(path)
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"got {base!r}", key="base", path=path, expected="a built-in scene name or a relative path")
    if _depth >= _MAX_BASE_DEPTH:
        raise ConfigError("inheritance chain too deep (a cycle?)", key="base", path=path)
    builtins = builtin_scenes()
    if base in builtins:
        base_path = builtins[base]
    else:
        base_path = (path.parent / base).resolve()
        if not base_path.is_file():
            raise ConfigError(f"base scene {base!r} not found", key="base", path=path,
                              expected="a built-in scene name or a path relative to this file")
    return merge_tables(_rig_for_type(resolve_inheritance(base_path, _depth=_depth + 1), data), data)


def _rig_for_type(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """`base` with its `[rig]` keys that do not apply to the rig type `override` switches to left out.

    Tables merge key by key, so a scene that changes the rig `type` of its base would otherwise inherit the
    base type's own keys (a `forward` rig's `extent`, ...) and be refused for keys it never wrote. The keys
    the new type takes (`look_at`, `up`, `seed`, ...) are still inherited.
    """
    rig, new = base.get("rig"), override.get("rig")
    if not (isinstance(rig, Mapping) and isinstance(new, Mapping)):
        return dict(base)
    new_type, old_type = new.get("type"), rig.get("type", "forward")
    if new_type == old_type or new_type not in RIG_KEYS:
        return dict(base)  # same type, or an unknown one (refused with its key when the scene is parsed)
    return {**base, "rig": {k: v for k, v in rig.items() if k in RIG_KEYS[new_type]}}


def parse_scene(data: Mapping[str, Any], *, path: Path | None = None) -> SceneSpec:
    """Validate a scene table (inheritance already resolved) into a `SceneSpec`.

    Raises:
        ConfigError: naming the file, the key path and what is expected.
    """
    for k in data:
        if k not in _ROOT_KEYS:
            raise ConfigError("unknown key", key=str(k), path=path, expected="one of " + ", ".join(_ROOT_KEYS))

    def table(name: str) -> Mapping[str, Any]:
        value = data.get(name, {})
        if not isinstance(value, Mapping):
            raise ConfigError(f"got {value!r}", key=name, path=path, expected="a table")
        return value

    rig_table = table("rig")
    rig_type = rig_table.get("type", "forward")
    if isinstance(rig_type, str) and rig_type in RIG_KEYS:
        for k in rig_table:
            if k != "type" and k not in RIG_KEYS[rig_type]:
                raise ConfigError(f"does not apply to a `{rig_type}` rig", key=join_key("rig", k), path=path,
                                  expected="one of " + ", ".join(sorted(RIG_KEYS[rig_type] | {"type"})))

    textures_table = table("textures")
    if not textures_table:
        raise ConfigError("no textures defined", key="textures", path=path,
                          expected="at least one [textures.NAME] table")
    textures = {}
    for name, t in textures_table.items():
        textures[str(name)] = _as(TextureSpec, t, f"textures.{name}", path)

    objects_list = data.get("objects")
    if not isinstance(objects_list, list) or not objects_list:
        raise ConfigError("no objects defined", key="objects", path=path,
                          expected="at least one [[objects]] table")
    objects = tuple(_as(ObjectSpec, o, f"objects[{i}]", path) for i, o in enumerate(objects_list))
    if path is not None:  # user meshes: relative to the scene file; stored absolute in the resolved spec
        objects = tuple(
            dataclasses.replace(o, path=str((path.parent / o.path).resolve()))
            if o.path is not None and not Path(o.path).is_absolute() else o
            for o in objects
        )
    names = set()
    for i, obj in enumerate(objects):
        if obj.texture not in textures:
            raise ConfigError(f"unknown texture {obj.texture!r}", key=f"objects[{i}].texture", path=path,
                              expected="one of " + ", ".join(sorted(textures)))
        if obj.name in names:
            raise ConfigError(f"duplicate object name {obj.name!r}", key=f"objects[{i}].name", path=path,
                              expected="unique names")
        names.add(obj.name)

    effects_list = data.get("effects", [])
    if not isinstance(effects_list, list):
        raise ConfigError(f"got {effects_list!r}", key="effects", path=path, expected="an array of tables")
    effects = tuple(parse_effect(e, key=f"effects[{i}]", path=path) for i, e in enumerate(effects_list))

    spec = SceneSpec(
        info=from_table(SceneInfo, table("scene"), key="scene", path=path),
        render=from_table(RenderSpec, table("render"), key="render", path=path),
        lighting=from_table(LightingSpec, table("lighting"), key="lighting", path=path),
        camera=from_table(CameraSpec, table("camera"), key="camera", path=path),
        rig=from_table(RigSpec, rig_table, key="rig", path=path),
        split=from_table(SplitSpec, table("split"), key="split", path=path),
        textures=textures,
        objects=objects,
        effects=effects,
        source=path,
    )
    _check_split(spec, path)
    return spec


def _as(cls: type, value: Any, key: str, path: Path | None) -> Any:
    if not isinstance(value, Mapping):
        raise ConfigError(f"got {value!r}", key=key, path=path, expected="a table")
    return from_table(cls, value, key=key, path=path)


def _check_split(spec: SceneSpec, path: Path | None) -> None:
    """The rig's views exist (a look-at camera needs an `up` off its viewing direction), the explicit test
    names are theirs, and the split leaves at least one training view (nothing trains on a scene without)."""
    from data_synth.rigs import rig_views, split_views

    try:
        views = rig_views(spec.rig)
    except DegenerateGeometryError as exc:
        # A list rig's poses each carry their own up and look-at; the other rigs' come from `rig.up`, `look_at`.
        key = "rig.poses" if spec.rig.type == "list" else "rig.up" if "`up`" in str(exc) else "rig"
        raise ConfigError(str(exc), key=key, path=path,
                          expected="an up vector not parallel to any camera's viewing direction, and a look-at "
                                   "point apart from every camera") from exc
    names = {v.name for v in views}
    for i, name in enumerate(spec.split.test or []):
        if name not in names:
            raise ConfigError(f"no view named {name!r}", key=f"split.test[{i}]", path=path,
                              expected="names of this rig's views (view_000, ...)")
    split = split_views([v.name for v in views], spec.split)
    if not split["train"]:
        raise ConfigError(f"the split leaves none of the {len(views)} view(s) for training "
                          f"(test: {', '.join(split['test'])})", key="split", path=path,
                          expected="more views (--views N) or fewer test views (split.test_every, split.test)")


def load_scene(scene: str | Path, *, seed: int | None = None, size_wh: tuple[int, int] | None = None,
               views: int | None = None) -> SceneSpec:
    """Find, read, resolve and validate a scene, then apply command-line overrides.

    Args:
        scene: a built-in name (see `builtin_scenes`) or a .toml path.
        seed: overrides `scene.seed`.
        size_wh: overrides `render.size` (W, H); the field of view is kept.
        views: overrides `rig.views` (not for `list` rigs).

    Raises:
        InputError / ConfigError: unknown scene, bad file, bad override.
    """
    path = find_scene(scene)
    data = resolve_inheritance(path)
    if seed is not None:
        data = merge_tables(data, {"scene": {"seed": int(seed)}})
    if size_wh is not None:
        data = merge_tables(data, {"render": {"size": [int(size_wh[0]), int(size_wh[1])]}})
    if views is not None:
        rig_type = data.get("rig", {}).get("type", "forward") if isinstance(data.get("rig"), Mapping) else "forward"
        if rig_type == "list":
            raise ConfigError("--views cannot change a `list` rig (its poses are explicit)", key="rig.views",
                              path=path, fix="edit [[rig.poses]] in the scene file instead")
        data = merge_tables(data, {"rig": {"views": int(views)}})
    return parse_scene(data, path=path)


def scene_to_table(spec: SceneSpec) -> dict[str, Any]:
    """The resolved scene as a TOML-ready dict (no `base`; defaults filled in)."""
    return {
        "scene": to_table(spec.info),
        "render": to_table(spec.render),
        "lighting": to_table(spec.lighting),
        "camera": to_table(spec.camera),
        "rig": _rig_table(spec.rig),
        "split": to_table(spec.split),
        "textures": {name: to_table(t) for name, t in spec.textures.items()},
        "objects": [to_table(o) for o in spec.objects],
        "effects": [effect_table(e) for e in spec.effects],
    }


def _rig_table(rig: RigSpec) -> dict[str, Any]:
    full = to_table(rig)
    keep = RIG_KEYS[rig.type] | {"type"}
    return {k: v for k, v in full.items() if k in keep}


def scene_to_toml(spec: SceneSpec) -> str:
    """The resolved scene as TOML text; `parse_scene(tomllib.loads(text))` gives back an equal spec."""
    header = f"# Resolved scene '{spec.info.name}' written by data_synth (inheritance flattened, defaults filled in).\n"
    return header + dumps(scene_to_table(spec))


