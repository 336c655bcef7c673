"""Typed scene specification: one frozen dataclass per TOML table.

A scene file has these tables (all optional except `objects` and `textures`):
`[scene]`, `[render]`, `[lighting]`, `[camera]`, `[rig]`, `[split]`,
`[textures.NAME]`, `[[objects]]`, `[[effects]]`, plus a top-level
`base = "NAME_OR_PATH"` that inherits another scene (tables merged key by key,
arrays such as `objects`/`effects` replaced whole). World units are metres
by convention; frames follow docs/conventions.md.

Every field's default is documented here; `data-synth show SCENE` prints the
resolved file.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from data_synth.schema import join_key, spec_field
from mvgeo.common.errors import ConfigError

SHAPES = ("plane", "box", "sphere", "cylinder", "terrain", "mesh")
PATTERNS = ("constant", "checker", "stripes", "noise", "turbulence")
RIG_TYPES = ("forward", "ring", "sphere", "list")
OUTPUTS = ("depth", "alpha", "normals")


def _require_nonzero(vec: tuple[float, ...], key: str, path: Path | None) -> None:
    if float(np.linalg.norm(vec)) < 1e-9:
        raise ConfigError("is the zero vector", key=key, path=path, expected="a non-zero direction")


@dataclass(frozen=True)
class SceneInfo:
    """`[scene]`: name, one-line description and the seed of the effects' random streams."""

    name: str = spec_field("unnamed", doc="scene name (shown by `data-synth list`)")
    description: str = spec_field("", doc="one line")
    seed: int = spec_field(0, range=(0, 2**32 - 1),
                           doc="seed of the effects' random streams only (geometry, textures and poses "
                               "are fixed by the file); overridden by --seed")


@dataclass(frozen=True)
class RenderSpec:
    """`[render]`: image size, antialiasing, background and extra outputs."""

    size: tuple[int, ...] = spec_field((504, 378), length=2, range=(8, 8192),
                                       doc="image (width, height) in pixels (LLFF 1/8 resolution)")
    supersample: int = spec_field(2, range=(1, 8), doc="n: n x n rays per pixel, box-filtered")
    background: tuple[float, ...] = spec_field((0.0, 0.0, 0.0), length=3, range=(0.0, 1.0),
                                               doc="RGB where rays miss every object")
    bit_depth: int = spec_field(8, range=(8, 16), doc="PNG bits per channel: 8 or 16")
    outputs: tuple[str, ...] = spec_field(("depth",), choices=OUTPUTS,
                                          doc="extra per-view outputs: depth (z, .npy), alpha, normals")

    def validated(self, *, key: str, path: Path | None) -> RenderSpec:
        if self.bit_depth not in (8, 16):
            raise ConfigError(f"got {self.bit_depth}", key=join_key(key, "bit_depth"), path=path, expected="8 or 16")
        return self


@dataclass(frozen=True)
class LightingSpec:
    """`[lighting]`: Lambertian shading with one directional light and an ambient term, or unlit."""

    mode: str = spec_field("lambert", choices=("lambert", "unlit"))
    direction: tuple[float, ...] = spec_field((0.3, -0.5, 1.0), length=3,
                                              doc="direction towards the light, world frame (normalised)")
    ambient: float = spec_field(0.35, range=(0.0, 1.0), doc="ambient term")
    intensity: float = spec_field(0.75, range=(0.0, 4.0), doc="directional term at normal incidence")

    def validated(self, *, key: str, path: Path | None) -> LightingSpec:
        _require_nonzero(self.direction, join_key(key, "direction"), path)
        return self


@dataclass(frozen=True)
class CameraSpec:
    """`[camera]`: pinhole intrinsics (principal point at the image centre), optional distortion."""

    fov_x_deg: float = spec_field(63.0, range=(1.0, 170.0),
                                  doc="horizontal field of view; fx = fy = (W/2) / tan(fov_x/2)")
    distortion: tuple[float, ...] | None = spec_field(
        None, length=4, range=(-1.0, 1.0),
        doc="OpenCV k1, k2, p1, p2; when set the camera model is OPENCV, otherwise PINHOLE")


@dataclass(frozen=True)
class PoseSpec:
    """One explicit pose of a `list` rig: a camera at `position` looking at `look_at`."""

    position: tuple[float, ...] = spec_field(length=3, doc="camera centre, world frame")
    look_at: tuple[float, ...] = spec_field(length=3, doc="point on the optical axis, world frame")
    up: tuple[float, ...] = spec_field((0.0, 0.0, 1.0), length=3, doc="world direction shown upwards")
    roll_deg: float = spec_field(0.0, range=(-180.0, 180.0), doc="rotation about the optical axis")
    name: str | None = spec_field(None, doc="view name (default view_NNN)")

    def validated(self, *, key: str, path: Path | None) -> PoseSpec:
        if float(np.linalg.norm(np.subtract(self.look_at, self.position))) < 1e-9:
            raise ConfigError("equals position", key=join_key(key, "look_at"), path=path,
                              expected="a point different from the camera centre")
        _require_nonzero(self.up, join_key(key, "up"), path)
        return self


RIG_KEYS = {
    "forward": {"center", "look_at", "up", "pattern", "extent", "depth_jitter", "position_jitter",
                "rotation_jitter_deg", "seed", "views"},
    "ring": {"look_at", "up", "radius", "height", "start_deg", "position_jitter", "rotation_jitter_deg",
             "seed", "views"},
    "sphere": {"look_at", "up", "radius", "elevation_deg", "position_jitter", "rotation_jitter_deg",
               "seed", "views"},
    "list": {"poses"},
}


@dataclass(frozen=True)
class RigSpec:
    """`[rig]`: where the cameras are.

    - `forward`: LLFF-like handheld forward-facing capture. Camera centres on a
      jittered grid (or a spiral) in the plane through `center` perpendicular
      to the viewing direction, half-extent `extent` (right, down); each looks
      at `look_at`, plus per-view position and rotation jitter.
    - `ring`: 360 degrees around `look_at` at `radius`, `height` above it.
    - `sphere`: a Fibonacci spiral over the band `elevation_deg` at `radius`.
    - `list`: explicit `[[rig.poses]]`.

    Jitter comes from `numpy.random.default_rng([seed, crc32(view name)])`, so a
    view's pose does not depend on how many views there are (grid and ring
    positions do, by construction).
    """

    type: str = spec_field("forward", choices=RIG_TYPES)
    views: int = spec_field(20, range=(1, 10000), doc="number of views (not for `list`)")
    center: tuple[float, ...] = spec_field((0.0, 0.0, 1.2), length=3, doc="forward: centre of the camera grid")
    look_at: tuple[float, ...] = spec_field((0.0, 4.0, 0.8), length=3, doc="point every camera looks at")
    up: tuple[float, ...] = spec_field((0.0, 0.0, 1.0), length=3, doc="world up (shown upwards in images)")
    pattern: str = spec_field("grid", choices=("grid", "spiral"), doc="forward: camera layout")
    extent: tuple[float, ...] = spec_field((0.3, 0.15), length=2, range=(0.0, None),
                                           doc="forward: half-extent (right, down) of the layout, scene units")
    depth_jitter: float = spec_field(0.05, range=(0.0, None), doc="forward: std of motion along the view axis")
    position_jitter: float = spec_field(0.02, range=(0.0, None), doc="std of per-view position noise, per world axis")
    rotation_jitter_deg: float = spec_field(1.0, range=(0.0, 45.0),
                                            doc="std of per-view rotation noise, per rotation-vector component")
    radius: float = spec_field(3.0, range=(0.0, None),
                               doc="ring: horizontal distance from look_at (perpendicular to up; the camera is "
                                   "sqrt(radius^2 + height^2) from look_at); sphere: distance to look_at")
    height: float = spec_field(1.0, doc="ring: camera height above look_at (along up)")
    start_deg: float = spec_field(0.0, doc="ring: azimuth of the first view, counter-clockwise about up from "
                                           "up x (1, 0, 0) (+y for up = +z; up x (0, 1, 0) when up is near x)")
    elevation_deg: tuple[float, ...] = spec_field((10.0, 60.0), length=2, range=(-90.0, 90.0),
                                                  doc="sphere: elevation band")
    seed: int = spec_field(0, range=(0, 2**32 - 1), doc="seed of the pose jitter")
    poses: tuple[PoseSpec, ...] = spec_field((), doc="list: explicit poses")

    def validated(self, *, key: str, path: Path | None) -> RigSpec:
        _require_nonzero(self.up, join_key(key, "up"), path)
        if self.type == "list" and not self.poses:
            raise ConfigError("a `list` rig needs at least one [[rig.poses]]", key=join_key(key, "poses"),
                              path=path, expected="a non-empty array of tables")
        if self.type != "list" and self.poses:
            raise ConfigError(f"only a `list` rig takes poses (this rig is `{self.type}`)",
                              key=join_key(key, "poses"), path=path, expected='type = "list"')
        if self.type == "forward" and np.linalg.norm(np.subtract(self.look_at, self.center)) < 1e-9:
            raise ConfigError("equals center", key=join_key(key, "look_at"), path=path,
                              expected="a point in front of the cameras")
        if self.type in ("ring", "sphere") and self.radius <= 0:
            raise ConfigError("must be positive", key=join_key(key, "radius"), path=path, expected="> 0")
        if self.elevation_deg[0] > self.elevation_deg[1]:
            raise ConfigError("min > max", key=join_key(key, "elevation_deg"), path=path,
                              expected="[min, max]")
        names = [p.name for p in self.poses if p.name is not None]
        if len(set(names)) != len(names):
            raise ConfigError("duplicate view names", key=join_key(key, "poses"), path=path,
                              expected="unique names")
        return self

    @property
    def num_views(self) -> int:
        return len(self.poses) if self.type == "list" else self.views


@dataclass(frozen=True)
class SplitSpec:
    """`[split]`: which views are held out for testing (LLFF convention: every 8th, starting at 0)."""

    test_every: int = spec_field(8, range=(0, None), doc="views i with i % test_every == 0 are test; 0: none")
    test: tuple[str, ...] | None = spec_field(None, doc="explicit test view names (overrides test_every)")


@dataclass(frozen=True)
class TextureSpec:
    """`[textures.NAME]`: a procedural solid texture, evaluated at the 3-D hit point
    in the object's local frame (no UV seams; identical in every view).

    `pattern` gives a scalar s in [0, 1] which the colour ramp `colors` maps to
    RGB (stops evenly spaced; `checker` and sharp `stripes` pick the first or
    last colour). `warp` distorts the pattern's domain with noise (marble/wood
    look). `detail` multiplies brightness by (1 + detail * fbm) at
    `detail_scale`: multi-octave fine grain, the texture denoising can lose.
    """

    pattern: str = spec_field("noise", choices=PATTERNS)
    colors: tuple[tuple[float, ...], ...] = spec_field(((0.2, 0.2, 0.2), (0.8, 0.8, 0.8)), item_length=3,
                                                       range=(0.0, 1.0), doc="colour ramp stops, RGB in [0, 1]")
    scale: float = spec_field(0.25, range=(1e-4, None), doc="feature size (cell, period, wavelength), scene units")
    axis: tuple[float, ...] = spec_field((1.0, 0.0, 0.0), length=3, doc="stripes: direction across the stripes")
    duty: float = spec_field(0.5, range=(0.0, 1.0), doc="stripes: fraction of each period in the first colour")
    octaves: int = spec_field(4, range=(1, 10), doc="noise/turbulence octaves (and warp octaves)")
    lacunarity: float = spec_field(2.0, range=(1.1, 4.0))
    gain: float = spec_field(0.5, range=(0.0, 1.0), doc="amplitude ratio between octaves")
    contrast: float = spec_field(1.0, range=(0.0, 10.0), doc="noise: spread of s around 0.5")
    warp: float = spec_field(0.0, range=(0.0, 10.0), doc="domain warp strength, in feature sizes")
    detail: float = spec_field(0.0, range=(0.0, 2.0), doc="fine-detail brightness modulation amplitude")
    detail_scale: float = spec_field(0.02, range=(1e-4, None), doc="fine-detail feature size, scene units")
    detail_octaves: int = spec_field(3, range=(1, 8))
    seed: int = spec_field(0, range=(0, 2**32 - 1))

    def validated(self, *, key: str, path: Path | None) -> TextureSpec:
        if len(self.colors) < 1:
            raise ConfigError("is empty", key=join_key(key, "colors"), path=path, expected="at least one RGB colour")
        if self.pattern == "stripes":
            _require_nonzero(self.axis, join_key(key, "axis"), path)
        return self


_SHAPE_KEYS = {
    "plane": {"size"},
    "box": {"size"},
    "sphere": {"radius", "resolution"},
    "cylinder": {"radius", "height", "resolution"},
    "terrain": {"size", "amplitude", "feature_size", "octaves", "resolution", "seed"},
    "mesh": {"path"},
}
_SIZE_LEN = {"plane": 2, "box": 3, "terrain": 2}
_COMMON_OBJECT_KEYS = {"name", "shape", "texture", "translate", "rotate_deg", "scale", "smooth"}


@dataclass(frozen=True)
class ObjectSpec:
    """`[[objects]]`: a mesh placed by `x_world = R(rotate_deg) @ (scale * x_local) + translate`.

    Local frames: `plane` lies in z = 0 (normal +z) with `size` (x, y); `box` is
    centred with `size` (x, y, z); `sphere` is centred; `cylinder` has its axis
    along z, centred, caps closed; `terrain` is a height field over `size` (x, y)
    with z = amplitude * fbm(x / feature_size, y / feature_size); `mesh` loads a
    .ply/.obj (path relative to the scene file). `rotate_deg` are extrinsic
    x, y, z Euler angles.
    """

    name: str = spec_field(doc="object name")
    shape: str = spec_field(choices=SHAPES)
    texture: str = spec_field(doc="a key of [textures]")
    translate: tuple[float, ...] = spec_field((0.0, 0.0, 0.0), length=3)
    rotate_deg: tuple[float, ...] = spec_field((0.0, 0.0, 0.0), length=3)
    scale: float = spec_field(1.0, range=(1e-6, None))
    smooth: bool | None = spec_field(None, doc="interpolate vertex normals (default: sphere, terrain, mesh)")
    size: tuple[float, ...] | None = spec_field(None, length=(2, 3), range=(1e-6, None))
    radius: float | None = spec_field(None, range=(1e-6, None))
    height: float | None = spec_field(None, range=(1e-6, None))
    resolution: int | None = spec_field(None, range=(3, 2048), doc="tessellation (segments / grid cells per side)")
    amplitude: float | None = spec_field(None, range=(0.0, None))
    feature_size: float | None = spec_field(None, range=(1e-4, None))
    octaves: int | None = spec_field(None, range=(1, 10))
    seed: int | None = spec_field(None, range=(0, 2**32 - 1))
    path: str | None = spec_field(None)

    def validated(self, *, key: str, path: Path | None) -> ObjectSpec:
        allowed = _SHAPE_KEYS[self.shape]
        for f in dataclasses.fields(self):
            if f.name in _COMMON_OBJECT_KEYS:
                continue
            if getattr(self, f.name) is not None and f.name not in allowed:
                raise ConfigError(f"does not apply to shape '{self.shape}'", key=join_key(key, f.name), path=path,
                                  expected="one of " + ", ".join(sorted(allowed | _COMMON_OBJECT_KEYS)))
        defaults: dict[str, Any] = {
            "sphere": {"resolution": 48},
            "cylinder": {"resolution": 64},
            "terrain": {"amplitude": 0.1, "feature_size": 1.0, "octaves": 4, "resolution": 128, "seed": 0},
        }.get(self.shape, {})
        obj = dataclasses.replace(self, **{k: v for k, v in defaults.items() if getattr(self, k) is None})
        required = {"plane": ("size",), "box": ("size",), "sphere": ("radius",), "cylinder": ("radius", "height"),
                    "terrain": ("size",), "mesh": ("path",)}[self.shape]
        for name in required:
            if getattr(obj, name) is None:
                raise ConfigError(f"missing for shape '{self.shape}'", key=join_key(key, name), path=path)
        if obj.size is not None and len(obj.size) != _SIZE_LEN[self.shape]:
            raise ConfigError(f"has {len(obj.size)} entries", key=join_key(key, "size"), path=path,
                              expected=f"{_SIZE_LEN[self.shape]} entries for shape '{self.shape}'")
        if obj.smooth is None:
            obj = dataclasses.replace(obj, smooth=self.shape in ("sphere", "terrain", "mesh"))
        return obj


@dataclass(frozen=True)
class EffectSpec:
    """`[[effects]]`: one degradation, `type` plus that effect's parameters (see data_synth.effects)."""

    type: str
    params: Any  # the effect's own frozen params dataclass


@dataclass(frozen=True)
class SceneSpec:
    """A resolved scene: every table validated, defaults filled in."""

    info: SceneInfo
    render: RenderSpec
    lighting: LightingSpec
    camera: CameraSpec
    rig: RigSpec
    split: SplitSpec
    textures: dict[str, TextureSpec]
    objects: tuple[ObjectSpec, ...]
    effects: tuple[EffectSpec, ...]
    source: Path | None = None
    """The file the scene came from (user mesh paths are relative to its folder)."""
