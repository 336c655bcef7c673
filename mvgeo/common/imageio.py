"""Image file I/O at the project's boundary (see docs/conventions.md).

Arrays are H x W x 3 float32 RGB in [0, 1]. cv2 does the decoding (BGR) and
we convert once here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def list_images(folder: str | Path) -> list[Path]:
    """Sorted image files (by name) directly inside `folder`.

    Raises:
        InputError: the folder is missing, not a folder, or holds no images.
    """
    folder = Path(folder)
    if not folder.exists():
        raise InputError("folder does not exist", path=folder, fix="pass a folder of images")
    if not folder.is_dir():
        raise InputError("not a folder", path=folder, fix="pass a folder of images")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder", path=folder,
                         fix="put PNG/JPEG images directly in this folder")
    return files


def read_image(path: str | Path, *, gray_to_rgb: bool = True) -> np.ndarray:
    """Read an 8/16-bit image as float32 RGB in [0, 1], shape (H, W, 3).

    Grayscale files are replicated to three channels; alpha is dropped.

    Raises:
        InputError: missing, unreadable or corrupt file (named).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("image file does not exist", path=path)
    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError("cannot decode image (corrupt or unsupported format)", path=path,
                         fix="re-export it as PNG or JPEG, or remove it from the folder")
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    else:
        raise InputError(f"unsupported pixel type {img.dtype}", path=path, fix="use 8- or 16-bit images")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.shape[2] == 4:
        img = img[:, :, :3]
    if img.shape[2] == 1:
        if not gray_to_rgb:
            return (img.astype(np.float32) / scale)
        img = np.repeat(img, 3, axis=2)
    else:
        img = img[:, :, ::-1]
    return np.ascontiguousarray(img.astype(np.float32) / np.float32(scale))


def to_uint(img: np.ndarray, bits: int = 8) -> np.ndarray:
    """[0, 1] float -> uint8/uint16 with rounding and clipping."""
    if bits not in (8, 16):
        raise ValueError("bits must be 8 or 16")
    maxv = 255 if bits == 8 else 65535
    dtype = np.uint8 if bits == 8 else np.uint16
    return np.clip(np.rint(np.asarray(img, dtype=np.float64) * maxv), 0, maxv).astype(dtype)


def write_image(path: str | Path, img: np.ndarray, *, bits: int = 8) -> None:
    """Write an (H, W, 3) or (H, W) float image in [0, 1] (RGB) as PNG/JPEG."""
    path = Path(path)
    arr = to_uint(img, bits)
    if arr.ndim == 3:
        arr = arr[:, :, ::-1]
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(path.suffix or ".png", np.ascontiguousarray(arr))
    if not ok:
        raise InputError("cannot encode image", path=path)
    buf.tofile(path)
