"""Camera rigs: ground-truth `cam_from_world` poses and view names, and the train/test split.

Poses follow docs/conventions.md: OpenCV camera axes (x right, y down, z
forward), `cam_from_world` (3, 4) float64 `[R | t]`.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from data_synth.spec import PoseSpec, RigSpec, SplitSpec
from mvgeo.common.errors import DegenerateGeometryError


@dataclass(frozen=True)
class View:
    """One ground-truth view: its name (file stem) and `cam_from_world` (3, 4) float64."""

    name: str
    cam_from_world: np.ndarray


def view_name(index: int) -> str:
    """Default view name of the `index`-th view (`view_000`)."""
    return f"view_{index:03d}"


def view_rng(seed: int, name: str, *extra: int) -> np.random.Generator:
    """A random stream keyed by (seed, view name, extra...): independent of other views and their count."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode("utf-8")), *map(int, extra)])


def look_at_cam_from_world(position: np.ndarray, target: np.ndarray, up: np.ndarray, *,
                           roll_rad: float = 0.0) -> np.ndarray:
    """`cam_from_world` (3, 4) float64 of a camera at `position` whose optical axis passes through `target`.

    `up` (world) appears upwards in the image (camera -y); `roll_rad` then
    rotates the camera about its optical axis (camera x turning towards camera y).

    Raises:
        DegenerateGeometryError: `target == position` or `up` parallel to the optical axis.
    """
    position = np.asarray(position, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - position
    norm = np.linalg.norm(forward)
    if norm < 1e-12:
        raise DegenerateGeometryError("look-at target coincides with the camera centre")
    z = forward / norm
    down = -np.asarray(up, dtype=np.float64)
    down = down - z * (down @ z)
    dn = np.linalg.norm(down)
    if dn < 1e-9:
        raise DegenerateGeometryError("`up` is parallel to the viewing direction; choose another up vector")
    y = down / dn
    x = np.cross(y, z)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    if roll_rad:
        c, s = math.cos(roll_rad), math.sin(roll_rad)
        R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ R
    t = -R @ position
    return np.hstack([R, t[:, None]])


def _jittered(cam_from_world: np.ndarray, rng: np.random.Generator, *, position_std: float,
              rotation_std_rad: float, axis_std: float = 0.0) -> np.ndarray:
    """Perturb a pose: centre moved by N(0, position_std^2) (plus `axis_std` along the optical
    axis), then a rotation of N(0, rotation_std^2) rotation vector left-multiplied in the camera frame."""
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    centre = -R.T @ t
    centre = centre + rng.normal(scale=position_std, size=3) + R[2] * rng.normal(scale=axis_std)
    dR = Rotation.from_rotvec(rng.normal(scale=rotation_std_rad, size=3)).as_matrix()
    R_new = dR @ R
    return np.hstack([R_new, (-R_new @ centre)[:, None]])


def _forward_offsets(rig: RigSpec) -> np.ndarray:
    """(views, 2) (right, down) offsets of the camera centres in the capture plane, scene units."""
    n = rig.views
    ex, ey = rig.extent
    if rig.pattern == "grid":
        aspect = ex / ey if ey > 0 else float(n)
        cols = max(1, min(n, math.ceil(math.sqrt(n * aspect))))
        rows = math.ceil(n / cols)
        xs = np.linspace(-ex, ex, cols) if cols > 1 else np.zeros(1)
        ys = np.linspace(-ey, ey, rows) if rows > 1 else np.zeros(1)
        grid = np.array([(x, y) for y in ys for x in xs])
        return grid[:n]
    # Spiral: two turns, radius growing from 30% to 100% of the extent.
    k = np.arange(n)
    frac = k / max(n - 1, 1)
    angle = 2 * 2 * math.pi * frac
    r = 0.3 + 0.7 * frac
    return np.stack([ex * r * np.cos(angle), ey * r * np.sin(angle)], axis=1)


def rig_views(rig: RigSpec) -> list[View]:
    """The ground-truth views of a rig, in order (see `RigSpec`)."""
    rot_std = math.radians(rig.rotation_jitter_deg)
    target = np.asarray(rig.look_at, dtype=np.float64)
    up = np.asarray(rig.up, dtype=np.float64)
    views: list[View] = []
    if rig.type == "list":
        for i, pose in enumerate(rig.poses):
            views.append(View(pose.name or view_name(i), _pose_from_spec(pose)))
        return views
    if rig.type == "forward":
        base = look_at_cam_from_world(np.asarray(rig.center, float), target, up)
        right, down = base[0, :3], base[1, :3]
        offsets = _forward_offsets(rig)
        for i, (dx, dy) in enumerate(offsets):
            name = view_name(i)
            centre = np.asarray(rig.center, float) + dx * right + dy * down
            pose = look_at_cam_from_world(centre, target, up)
            pose = _jittered(pose, view_rng(rig.seed, name), position_std=rig.position_jitter,
                             rotation_std_rad=rot_std, axis_std=rig.depth_jitter)
            views.append(View(name, pose))
        return views
    up_unit = up / np.linalg.norm(up)
    # Two horizontal directions orthogonal to up.
    helper = np.array([1.0, 0.0, 0.0]) if abs(up_unit[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up_unit, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up_unit, e1)
    for i in range(rig.views):
        name = view_name(i)
        if rig.type == "ring":
            az = math.radians(rig.start_deg) + 2 * math.pi * i / rig.views
            centre = target + rig.radius * (math.cos(az) * e1 + math.sin(az) * e2) + rig.height * up_unit
        else:  # sphere: Fibonacci spiral over the elevation band
            lo, hi = (math.radians(a) for a in rig.elevation_deg)
            s = (i + 0.5) / rig.views
            elev = math.asin(math.sin(lo) + s * (math.sin(hi) - math.sin(lo)))
            az = i * math.pi * (3 - math.sqrt(5))
            horiz = math.cos(elev) * (math.cos(az) * e1 + math.sin(az) * e2)
            centre = target + rig.radius * (horiz + math.sin(elev) * up_unit)
        pose = look_at_cam_from_world(centre, target, up)
        pose = _jittered(pose, view_rng(rig.seed, name), position_std=rig.position_jitter, rotation_std_rad=rot_std)
        views.append(View(name, pose))
    return views


def _pose_from_spec(pose: PoseSpec) -> np.ndarray:
    return look_at_cam_from_world(np.asarray(pose.position, float), np.asarray(pose.look_at, float),
                                  np.asarray(pose.up, float), roll_rad=math.radians(pose.roll_deg))


def split_views(names: list[str], split: SplitSpec) -> dict[str, list[str]]:
    """`{"train": [...], "test": [...]}`; LLFF convention by default (view i is test when i % 8 == 0).

    Names in an explicit `split.test` are checked against the rig when the scene is parsed.
    """
    if split.test is not None:
        test_set = set(split.test)
    elif split.test_every > 0:
        test_set = {n for i, n in enumerate(names) if i % split.test_every == 0}
    else:
        test_set = set()
    return {"train": [n for n in names if n not in test_set], "test": [n for n in names if n in test_set]}
