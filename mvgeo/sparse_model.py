"""COLMAP sparse models (`sparse/0/`): the one place that reads and writes them.

Everything goes through pycolmap, so text and binary files are exactly what
COLMAP writes. Poses are `cam_from_world` (3, 4) float64 `[R | t]`, our
quaternions are wxyz; pycolmap's `Rigid3d` is xyzw and is converted here only.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mvgeo.camera import Camera
from mvgeo.common.deps import pycolmap
from mvgeo.common.errors import InputError


@dataclass
class PosedImage:
    """One registered image.

    Attributes:
        name: file name relative to the images folder (e.g. "000.png").
        camera_id: key into `SparseModel.cameras`.
        cam_from_world: (3, 4) float64 `[R | t]`, x_cam = R x_world + t.
    """

    name: str
    camera_id: int
    cam_from_world: np.ndarray

    def __post_init__(self) -> None:
        m = np.asarray(self.cam_from_world, dtype=np.float64)
        if m.shape == (4, 4):
            m = m[:3]
        if m.shape != (3, 4):
            raise InputError(f"cam_from_world of image {self.name!r} must be (3, 4) or (4, 4), got {m.shape}")
        self.cam_from_world = m

    @property
    def R(self) -> np.ndarray:
        return self.cam_from_world[:, :3]

    @property
    def t(self) -> np.ndarray:
        return self.cam_from_world[:, 3]

    @property
    def centre_world(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, -R^T t."""
        return -self.R.T @ self.t


@dataclass
class SparseModel:
    """Cameras, registered images (sorted by name) and an optional point cloud.

    Attributes:
        cameras: camera_id -> Camera.
        images: registered images.
        points_xyz: (P, 3) float64 world points (may be empty).
        points_rgb: (P, 3) uint8 colours.
    """

    cameras: dict[int, Camera]
    images: list[PosedImage]
    points_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    points_rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))

    def __post_init__(self) -> None:
        self.images = sorted(self.images, key=lambda im: im.name)
        self.points_xyz = np.asarray(self.points_xyz, dtype=np.float64).reshape(-1, 3)
        self.points_rgb = np.asarray(self.points_rgb, dtype=np.uint8).reshape(-1, 3)
        if len(self.points_xyz) != len(self.points_rgb):
            raise InputError("points_xyz and points_rgb must have the same length")
        for im in self.images:
            if im.camera_id not in self.cameras:
                raise InputError(f"image {im.name!r} refers to missing camera {im.camera_id}")

    @property
    def names(self) -> list[str]:
        return [im.name for im in self.images]

    def image(self, name: str) -> PosedImage:
        for im in self.images:
            if im.name == name:
                return im
        raise KeyError(name)

    def camera_of(self, name: str) -> Camera:
        return self.cameras[self.image(name).camera_id]

    def cam_from_world_by_name(self) -> dict[str, np.ndarray]:
        """name -> (3, 4) cam_from_world (the input of `mvgeo.metrics.compare_poses`)."""
        return {im.name: im.cam_from_world.copy() for im in self.images}


def _quat_wxyz_from_R(R: np.ndarray) -> np.ndarray:
    # local to avoid depending on mvgeo.transforms from the I/O layer; robust (Shepperd) method
    from scipy.spatial.transform import Rotation

    q_xyzw = Rotation.from_matrix(R).as_quat()
    q = np.array([q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]])
    return q if q[0] >= 0 else -q


def _rigid3d_from_cam_from_world(m: np.ndarray):
    q = _quat_wxyz_from_R(m[:, :3])
    xyzw = np.array([q[1], q[2], q[3], q[0]])  # pycolmap Rotation3d takes xyzw
    return pycolmap.Rigid3d(pycolmap.Rotation3d(xyzw), m[:, 3].copy())


def to_pycolmap(model: SparseModel):
    """Build a `pycolmap.Reconstruction` (trivial rigs/frames, one per camera/image)."""
    rec = pycolmap.Reconstruction()
    for cam_id, cam in model.cameras.items():
        pc = pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height, params=cam.params.copy(),
                             camera_id=int(cam_id))
        rec.add_camera_with_trivial_rig(pc)
    for image_id, im in enumerate(model.images, start=1):
        pim = pycolmap.Image(name=im.name, camera_id=int(im.camera_id), image_id=image_id)
        rec.add_image_with_trivial_frame(pim, _rigid3d_from_cam_from_world(im.cam_from_world))
    for xyz, rgb in zip(model.points_xyz, model.points_rgb, strict=True):
        rec.add_point3D(np.asarray(xyz, np.float64), pycolmap.Track(), np.asarray(rgb, np.uint8))
    return rec


def from_pycolmap(rec) -> SparseModel:
    """Convert a `pycolmap.Reconstruction` (registered images only)."""
    cameras = {
        int(cid): Camera(cam.model.name, cam.width, cam.height, np.asarray(cam.params, np.float64))
        for cid, cam in rec.cameras.items()
    }
    images = []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        m = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        images.append(PosedImage(image.name, int(image.camera_id), m))
    if rec.num_points3D():
        pts = list(rec.points3D.values())
        xyz = np.array([p.xyz for p in pts], dtype=np.float64)
        rgb = np.array([p.color for p in pts], dtype=np.uint8)
    else:
        xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return SparseModel(cameras, images, xyz, rgb)


def read_sparse_model(path: str | Path) -> SparseModel:
    """Read a COLMAP model folder (`cameras`, `images`, `points3D` as .bin or .txt).

    Raises:
        InputError: the folder or its files are missing or unreadable.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError("is a file, not a COLMAP model folder", path=path,
                         fix="pass the folder that holds cameras/images/points3D .bin or .txt (e.g. sparse/0)")
    if not path.is_dir():
        raise InputError("COLMAP model folder does not exist", path=path,
                         fix="pass a folder holding cameras/images/points3D .bin or .txt (e.g. sparse/0)")
    has_bin = all((path / f"{n}.bin").is_file() for n in ("cameras", "images", "points3D"))
    has_txt = all((path / f"{n}.txt").is_file() for n in ("cameras", "images", "points3D"))
    if not (has_bin or has_txt):
        raise InputError("no complete COLMAP model (cameras, images, points3D as .bin or .txt)", path=path,
                         fix="point at the sparse/0 folder of a COLMAP or mvgeo/data-synth output")
    fix = ("re-create the model (rerun the command that wrote it, or convert it again with "
           "`colmap model_converter`), or restore the file from a copy")
    if has_bin:  # pycolmap reads a truncated cameras.bin without complaint (garbage parameters)
        problem = cameras_bin_problem(path / "cameras.bin")
        if problem is not None:
            raise InputError(f"corrupt COLMAP cameras file: {problem}", path=path / "cameras.bin", fix=fix)
    if has_txt and not has_bin:  # pycolmap reads a text model with a line missing without complaint
        problem = images_txt_problem(path / "images.txt")
        if problem is not None:
            raise InputError(f"corrupt COLMAP images file: {problem}", path=path / "images.txt", fix=fix)
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:  # pycolmap raises plain exceptions (internal check text) on corrupt files
        files = ", ".join(f"{n}.{'bin' if has_bin else 'txt'}" for n in ("cameras", "images", "points3D"))
        raise InputError(f"cannot read the COLMAP model ({files}): a file is corrupt or inconsistent "
                         f"(pycolmap: {str(exc).strip()})", path=path, fix=fix) from exc
    try:
        return from_pycolmap(rec)
    except InputError as exc:  # e.g. a camera of no size (a negative width reads as a huge unsigned one)
        if exc.path is not None:
            raise
        raise InputError(f"the COLMAP model cannot be used: {exc.message}", path=path,
                         fix=exc.fix or fix) from exc


def _numbers(tokens: list[str]) -> bool:
    try:
        return all(math.isfinite(float(t)) for t in tokens)
    except ValueError:
        return False


def images_txt_problem(path: str | Path) -> str | None:
    """What is wrong with a COLMAP text `images.txt`, or None when its structure is sound.

    Layout (COLMAP `WriteImagesText`): comment lines (``#``; ``# Number of images: N, ...`` in COLMAP's own),
    then two lines per image: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` and its POINTS2D as
    ``X Y POINT3D_ID`` triples (an empty line without points). COLMAP's reader, as pycolmap's, skips blank lines
    only before an image line and takes the next line as its points whatever it holds: with one line missing,
    an image line is read as points and the image vanishes without an error.
    """
    lines = Path(path).read_text(encoding="utf-8", errors="replace").splitlines()
    declared, n, k = None, 0, 0
    while k < len(lines):
        line = lines[k].strip()
        k += 1
        if line.startswith("#"):
            m = re.match(r"#\s*Number of images:\s*(\d+)", line)
            declared = int(m[1]) if m else declared
            continue
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 10 or not _numbers(tokens[:9]):
            return (f"line {k} is not an image line (IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME): "
                    f"{line[:100]!r}")
        n += 1
        if k == len(lines):  # the last image without its points line: COLMAP reads it as an image without points
            break
        points = lines[k].split()
        k += 1
        if len(points) % 3 or not _numbers(points):
            return (f"line {k}, the POINTS2D line of image {' '.join(tokens[9:])!r}, is not (X, Y, POINT3D_ID) "
                    f"triples: {lines[k - 1].strip()[:100]!r} (a line missing above it? Every image takes two "
                    "lines, the second empty where it has no points)")
    if declared is not None and declared != n:
        return f"the header says {declared} image(s), the file holds {n}"
    return None


def cameras_bin_problem(path: str | Path) -> str | None:
    """What is wrong with a COLMAP binary `cameras.bin`, or None when its structure is sound.

    Layout (COLMAP `WriteCamerasBinary`, little endian): ``uint64`` camera count, then per camera
    ``uint32`` id, ``int32`` model id, ``uint64`` width, ``uint64`` height and the model's
    ``float64`` parameters; nothing after the last camera.
    """
    data = Path(path).read_bytes()
    if len(data) < 8:
        return f"{len(data)} bytes, shorter than the 8-byte camera count"
    count = int.from_bytes(data[:8], "little")
    offset = 8
    for i in range(count):
        if len(data) < offset + 24:
            return f"truncated: the header says {count} camera(s), the data ends inside camera {i}"
        model_id = int.from_bytes(data[offset + 4:offset + 8], "little", signed=True)
        width = int.from_bytes(data[offset + 8:offset + 16], "little")
        height = int.from_bytes(data[offset + 16:offset + 24], "little")
        n_params = _camera_model_num_params(model_id)
        if n_params is None:
            return f"camera {i}: unknown camera model id {model_id}"
        if width == 0 or height == 0:
            return f"camera {i}: image size {width}x{height}"
        offset += 24 + 8 * n_params
        if len(data) < offset:
            return f"truncated: the header says {count} camera(s), the data ends inside camera {i}"
    if len(data) != offset:
        return f"{len(data) - offset} unexpected bytes after the {count} camera(s) the header announces"
    return None


def _camera_model_num_params(model_id: int) -> int | None:
    """Number of parameters of a COLMAP camera model id (None: not a model pycolmap knows)."""
    known = {int(v): v for k, v in pycolmap.CameraModelId.__members__.items() if int(v) >= 0}
    if model_id not in known:
        return None
    return int(pycolmap.Camera.create_from_model_id(0, known[model_id], 1.0, 1, 1).params.size)


def write_sparse_model(path: str | Path, model: SparseModel, *, binary: bool) -> None:
    """Write `model` as a COLMAP model into folder `path` (created if needed)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    rec = to_pycolmap(model)
    if binary:
        rec.write_binary(str(path))
    else:
        rec.write_text(str(path))
