"""DTU captures in the IDR / MonoSDF layout: `images/*.png` plus `cameras.npz`.

`cameras.npz` holds, per view index i (image `00000i.png`: the index is the
image's file name; for names that are not numbers, the i-th image in sorted
order, and then the file must hold exactly one camera per image),
`world_mat_i` (4 x 4; its top 3 x 4 is the projection ``K [R | t]`` of the
original 1600 x 1200 image, world units mm) and `scale_mat_i` (maps the unit
sphere around the object to world coordinates). We use the normalised world
(object inside the unit sphere): ``P = world_mat[:3] @ scale_mat``, its sign
chosen so that its left 3 x 3 has a positive determinant (a projection is
defined up to scale, sign included), decomposed into ``K [R | t]`` (OpenCV
axes, pixel centres at integers as OpenCV's).

Pixels: for MonoSDF's 384 x 384 images (a centre crop of 1200 x 1200, then a
resize) K is mapped with ``u' = 0.32 (u - 200)``, ``v' = 0.32 v`` (the
README's formula); for the original 1600 x 1200 images it is kept. Then +0.5
px moves the principal point to our convention. The half-pixel conventions of
the original crop are not documented.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from eval.real.capture import BoundingSphere, Capture, CaptureView, image_size_wh
from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.npyio import load_numpy

__all__ = ["camera_indices", "dtu_cameras", "read_dtu"]

_WORLD_MAT = re.compile(r"world_mat_\d+")
_NPZ_FIX = "restore cameras.npz from the dataset's download (world_mat_i / scale_mat_i arrays)"

#: Original DTU pixels -> MonoSDF's 384 x 384 crop (both with pixel centres at integers).
CROP_384 = np.array([[0.32, 0.0, -0.32 * 200.0], [0.0, 0.32, 0.0], [0.0, 0.0, 1.0]])


def dtu_cameras(npz_path: Path, n: int | Sequence[int], *, size_wh: tuple[int, int] = (384, 384)
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(K (3, 3) in our pixel convention for images of `size_wh`, cam_from_world (3, 4)) for views 0..n-1,
    or for the view indices `n` (a sequence).

    Raises:
        InputError: a `world_mat_i` / `scale_mat_i` is missing or not 4 x 4, an unsupported image size,
            or a projection that decomposes to a reflection.
    """
    indices = list(range(n)) if isinstance(n, int) else [int(i) for i in n]
    npz_path = Path(npz_path)
    if tuple(size_wh) == (384, 384):
        to_pixels = CROP_384
    elif tuple(size_wh) == (1600, 1200):
        to_pixels = np.eye(3)
    else:
        raise InputError(f"DTU images are {size_wh[0]}x{size_wh[1]}; the cameras fit the original 1600x1200 "
                         "images or MonoSDF's 384x384 crop", path=npz_path,
                         fix="import the original or the 384x384 images and resize with --size / --max-size")
    data = load_numpy(npz_path, fix=_NPZ_FIX)
    out = []
    for i in indices:
        keys = (f"world_mat_{i}", f"scale_mat_{i}")
        arrays = []
        for key in keys:
            if key not in data:
                raise InputError(f"cameras.npz has no {key} (the camera of image {i})", path=npz_path,
                                 fix="keep one world_mat_i / scale_mat_i per image in images/")
            try:
                arrays.append(np.asarray(data[key]))
            except ValueError as exc:  # an object array, which loading without pickles refuses
                raise InputError(f"{key} is not a number array", path=npz_path, fix=_NPZ_FIX) from exc
            if arrays[-1].shape != (4, 4) or not np.issubdtype(arrays[-1].dtype, np.number):
                raise InputError(f"{key} must be a 4x4 number array, got shape {arrays[-1].shape} dtype "
                                 f"{arrays[-1].dtype}", path=npz_path)
        world, scale = (a.astype(np.float64) for a in arrays)
        finite = np.isfinite(world).all() and np.isfinite(scale).all()  # before the product: no NaN warnings
        P = (world @ scale)[:3] if finite else None
        if P is None or abs(np.linalg.det(P[:, :3] / max(np.abs(P[:, :3]).max(), 1e-300))) <= 1e-12:
            raise InputError(f"view {i}: world_mat_{i} @ scale_mat_{i} is not a camera projection (its left 3x3 "
                             "is singular or not finite)", path=npz_path,
                             fix=f"check world_mat_{i} and scale_mat_{i}")
        if np.linalg.det(P[:, :3]) < 0:  # P and -P are the same projection; K [R | t] has det(K R) > 0
            P = -P
        K, R, c_h = cv2.decomposeProjectionMatrix(P)[:3]
        K = K / K[2, 2]
        if np.linalg.det(R) < 0:
            raise InputError(f"view {i}: projection decomposes to a reflection", path=npz_path)
        # A pinhole camera holds no skew: dropping it moves a pixel by |skew| |y| (y normalised, up to the
        # image's half-height over fy); refused past 0.05 px (scan24's moves pixels by 3e-5 px).
        skew_px = abs(K[0, 1]) * 600.0 / abs(K[1, 1])
        if skew_px > 0.05:
            raise InputError(f"view {i}: the camera has skew ({K[0, 1]:g}: {skew_px:.2g} px at the image's edge), "
                             "which a pinhole camera cannot hold", path=npz_path,
                             fix="undistort/resample the images to a camera without skew first")
        C = (c_h[:3] / c_h[3]).reshape(3)
        K_px = to_pixels @ K
        K_px[0, 2] += 0.5
        K_px[1, 2] += 0.5
        out.append((K_px, np.hstack([R, (-R @ C)[:, None]])))
    return out


def camera_indices(files: Sequence[Path], npz_path: Path) -> list[int]:
    """The `cameras.npz` index of each image: its file name's number (`000012.png` -> 12) when every name is
    one and has its `world_mat_<number>` (the IDR/MonoSDF layout), else its position in sorted order, which
    needs exactly one camera per image (else a view would get another view's camera: an images folder with a
    gap shifts every later view)."""
    cameras = {int(k[len("world_mat_"):]) for k in load_numpy(npz_path, fix=_NPZ_FIX).files if _WORLD_MAT.fullmatch(k)}
    stems = [f.stem for f in files]
    if all(s.isdigit() for s in stems) and {int(s) for s in stems} <= cameras:
        return [int(s) for s in stems]
    if len(cameras) != len(files):
        raise InputError(f"{len(files)} images, {len(cameras)} cameras, and the images' names are not all "
                         "camera numbers: which camera is which image is ambiguous", path=npz_path,
                         fix="name the images by their camera index (000000.png for world_mat_0, ...), as the "
                             "IDR/MonoSDF layout does")
    return list(range(len(files)))


def read_dtu(src: str | Path) -> Capture:
    """Read a DTU scan folder (`images/*.png`, `cameras.npz`); the world is normalised by `scale_mat`.

    Returns:
        The capture; views in index order, named by the image stems; the bounding sphere is the unit
        sphere.

    Raises:
        InputError: see `dtu_cameras`; also missing files or images of different sizes.
    """
    src = Path(src)
    files = sorted((src / "images").glob("*.png")) if (src / "images").is_dir() else []
    if not files or not (src / "cameras.npz").is_file():
        raise InputError("not a DTU scan folder (needs images/*.png and cameras.npz)", path=src,
                         fix="point at a folder in the IDR/MonoSDF layout (images/000000.png..., cameras.npz)")
    sizes = {image_size_wh(f) for f in files}
    if len(sizes) != 1:
        raise InputError(f"the images have different sizes {sorted(sizes)}", path=src / "images")
    (size_wh,) = sizes
    cams = dtu_cameras(src / "cameras.npz", camera_indices(files, src / "cameras.npz"), size_wh=size_wh)
    views = [CaptureView(name=f.stem, image_path=f, camera=Camera.from_K(K, *size_wh), cam_from_world=cfw)
             for f, (K, cfw) in zip(files, cams, strict=True)]
    notes = ("DTU P = world_mat @ scale_mat decomposed; 384x384: u' = 0.32 (u - 200), v' = 0.32 v; "
             "principal point + 0.5 px (OpenCV pixel centres)",)
    return Capture(kind="dtu", source=src, views=views, world_units="DTU mm / scale_mat (object in the unit sphere)",
                   sphere=BoundingSphere((0.0, 0.0, 0.0), 1.0), notes=notes)
