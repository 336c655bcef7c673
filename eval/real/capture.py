"""What every real-capture reader returns: views with their image file, intrinsics and pose.

A reader only parses its format and converts it to the project's conventions
(docs/conventions.md: OpenCV camera axes, `cam_from_world`, the top-left
pixel's centre at (0.5, 0.5)); choosing views, resizing, degrading and
writing the dataset layout happen in `eval.real.layout`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mvgeo.camera import Camera
from mvgeo.common.errors import InputError


@dataclass(frozen=True)
class CaptureView:
    """One photograph with its ground-truth camera.

    Attributes:
        name: output file stem, unique in the capture (the source file's stem, "/" replaced by "_").
        image_path: the source image file (exists: readers check).
        camera: intrinsics for the image as stored in `image_path` (its width x height).
        cam_from_world: (4, 4) float64, OpenCV camera axes, world units of the capture.
        near_far: (near, far) z-depth bounds of the scene in this view (world units), when the
            format records them (LLFF), else None.
    """

    name: str
    image_path: Path
    camera: Camera
    cam_from_world: np.ndarray
    near_far: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        m = np.asarray(self.cam_from_world, dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4):
            raise InputError(f"cam_from_world of view {self.name!r} must be (3, 4) or (4, 4), got {m.shape}")
        object.__setattr__(self, "cam_from_world", m)


@dataclass(frozen=True)
class BoundingSphere:
    """A sphere around the scene's object, in world units: `centre_world` (3,), `radius`."""

    centre_world: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class Capture:
    """A photographed scene with known cameras, in the project's conventions.

    Attributes:
        kind: the reader that produced it ("llff", "colmap", "middlebury", "dtu").
        source: the folder or file it was read from.
        views: the views in the format's own order (LLFF: sorted image names, Middlebury: file
            order, DTU: index order, COLMAP: sorted names).
        world_units: what one world unit is ("unknown" when the format does not say).
        sphere: a bounding sphere of the object, when the format defines one (DTU), else None.
        notes: conversions applied, recorded in meta.json (pixel convention, axis order, crop).
        points_xyz: (P, 3) world points the source model holds (COLMAP), possibly empty.
        points_rgb: (P, 3) uint8 colours of `points_xyz`.
    """

    kind: str
    source: Path
    views: list[CaptureView]
    world_units: str = "unknown"
    sphere: BoundingSphere | None = None
    notes: tuple[str, ...] = ()
    points_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    points_rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))

    def __post_init__(self) -> None:
        if not self.views:
            raise InputError(f"the {self.kind} capture has no views", path=self.source,
                             fix="point at a capture whose camera file lists its images")
        for v in self.views:
            _check_camera(v, self.kind, self.source)
        names = [v.name for v in self.views]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise InputError(f"two views would be written under the same name: {', '.join(dupes)}",
                             path=self.source, fix="give the source images distinct file stems")

    @property
    def inputs(self) -> tuple[Path, ...]:
        """Every path the capture was read from (the source and the images' folders): an output must not touch them."""
        return tuple(dict.fromkeys([Path(self.source), *(v.image_path.parent for v in self.views)]))


#: Where each reader finds the cameras (named in the errors of `_check_camera`).
CAMERA_FILES = {"llff": "poses_bounds.npy", "colmap": "the model's cameras.txt / cameras.bin and images.*",
                "middlebury": "the *_par.txt file", "dtu": "cameras.npz"}


def _check_camera(view: CaptureView, kind: str, source: Path) -> None:
    """Refuse a camera no image can have: a focal length that is not a positive finite number, a
    non-finite parameter or pose (e.g. an all-zero DTU `world_mat`, a COLMAP focal of 0)."""
    cam = view.camera
    where = CAMERA_FILES.get(kind, "the camera file")
    fix = f"check view {view.name!r} in {where}"
    if not np.all(np.isfinite(cam.params)):
        raise InputError(f"view {view.name!r}: camera parameters {cam.params.tolist()} are not all finite",
                         path=source, fix=fix)
    if not (cam.fx > 0 and cam.fy > 0):
        raise InputError(f"view {view.name!r}: focal length {cam.fx:g} x {cam.fy:g} px; it must be positive",
                         path=source, fix=fix)
    if not np.all(np.isfinite(view.cam_from_world)):
        raise InputError(f"view {view.name!r}: its pose (cam_from_world) is not finite", path=source, fix=fix)


def rotation_checked(R: np.ndarray, *, what: str, path: Path, tol: float = 1e-5) -> np.ndarray:
    """`R` (3, 3) if it is a proper rotation to `tol` (max |R^T R - I|, det), re-orthonormalised (SVD).

    Raises:
        InputError: not a rotation (names `what`, e.g. "line 3", and the file).
    """
    R = np.asarray(R, dtype=np.float64)
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if not np.all(np.isfinite(R)) or err > tol or np.linalg.det(R) <= 0:
        raise InputError(f"{what}: the rotation is not orthonormal with det +1 (max |R^T R - I| = {err:.2g}, "
                         f"det = {np.linalg.det(R):.4g})", path=path,
                         fix="check the column order of the file; a reflection means a left-handed frame")
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def image_size_wh(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, read from its header (no decoding).

    Raises:
        InputError: the file is missing or not an image.
    """
    from PIL import Image, UnidentifiedImageError  # pillow ships with matplotlib, a dependency

    path = Path(path)
    if not path.is_file():
        raise InputError("image file does not exist", path=path,
                         fix="the cameras file names this image: restore it or remove its entry")
    try:
        with Image.open(path) as im:
            return int(im.width), int(im.height)
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(f"cannot read the image header ({exc})", path=path,
                         fix="re-export it as PNG or JPEG") from exc
