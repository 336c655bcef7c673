"""Middlebury multi-view stereo captures: `*_par.txt` plus the images beside it.

File format (Seitz et al., "A comparison and evaluation of multi-view stereo
reconstruction algorithms", the `templeSR`/`dinoSR` sets): the first line is
the number of views; then one line per image,

    name k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3

with the projection ``K [R | t]``: `R`, `t` map world to camera in OpenCV
axes (x right, y down, z forward), so ``cam_from_world = [R | t]`` unchanged.
The image origin is the top-left corner, x to the right, y down.

Pixel convention: the file's K puts the centre of the top-left pixel at
(0, 0) (integer coordinates at pixel centres, as OpenCV); ours puts it at
(0.5, 0.5), so ``cx = k13 + 0.5``, ``cy = k23 + 0.5`` (`PIXEL_OFFSET_PX`).
Checked on templeSparseRing with `eval.real.check` (SIFT tracks over view
triplets triangulated from two views with the file's cameras, median
transfer error in the third; several views are rotated 180 degrees in the
image plane, so a principal-point shift common to all views cannot be
absorbed by moving the points): shifting cx by -0.5, 0, +0.5, +1 px from
``k13 + 0.5`` gives 0.427, 0.420, 0.425, 0.427 px (cy kept): nearly flat,
lowest at ours. In y the error keeps falling up to about +1 px beyond
``k23 + 0.5`` (0.420 -> 0.274 px, cx kept), then rises: a bias of the
calibration larger than any half-pixel convention, which the importer does
not fit (the file's cameras are the ground truth as published).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eval.real.capture import Capture, CaptureView, image_size_wh, rotation_checked
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError

__all__ = ["PIXEL_OFFSET_PX", "find_par_file", "read_middlebury"]

#: Added to the file's principal point to get ours (file: pixel centres at integers).
PIXEL_OFFSET_PX = 0.5
_FIELDS = 1 + 9 + 9 + 3


#: The fix of a malformed camera file: its layout.
_PAR_FIX = ("write it as Middlebury's *_par.txt: the number of views on the first line, then per view one line "
            "NAME k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 ... r33 t1 t2 t3 (21 numbers after the name: "
            "K, then R and t of x_cam = R x_world + t)")


def find_par_file(src: Path) -> Path:
    """The `*_par.txt` file: `src` itself, or the only one inside folder `src`.

    Raises:
        InputError: none, or several, in the folder.
    """
    src = Path(src)
    if src.is_file():
        return src
    if not src.is_dir():
        raise InputError("Middlebury capture does not exist", path=src,
                         fix="pass the folder that holds the *_par.txt camera file and the images, or that file")
    found = sorted(src.glob("*_par.txt"))
    if len(found) != 1:
        raise InputError(f"expected one *_par.txt camera file in the folder, found {len(found)}"
                         + (f" ({', '.join(p.name for p in found)})" if found else ""), path=src,
                         fix="pass the *_par.txt file itself")
    return found[0]


def read_middlebury(src: str | Path) -> Capture:
    """Read a Middlebury capture: a `*_par.txt` file (or the folder holding exactly one) and its images.

    Image names are relative to the camera file's folder.

    Returns:
        The capture; views in file order.

    Raises:
        InputError: a missing file, a header that is not the view count, a line with the wrong number of
            fields or a non-number (file:line named), K with skew or a bad last row, a non-rotation, a
            missing image.
    """
    par = find_par_file(Path(src))
    try:
        text = par.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the camera file ({getattr(exc, 'strerror', None) or exc})", path=par,
                         fix="check that it is a readable text file (Middlebury's *_par.txt)") from exc
    lines = [(i + 1, ln.split()) for i, ln in enumerate(text.splitlines()) if ln.strip()]
    if not lines:
        raise InputError("the camera file is empty", path=par, fix=_PAR_FIX)
    head_no, head = lines[0]
    if len(head) != 1 or not head[0].isdigit():
        raise InputError(f"line {head_no}: the first line must be the number of views, got {' '.join(head)!r}",
                         path=par, fix=_PAR_FIX)
    count = int(head[0])
    body = lines[1:]
    if len(body) != count:
        raise InputError(f"line {head_no} announces {count} views but {len(body)} camera lines follow", path=par,
                         fix="make the first line the number of camera lines")
    views = []
    for line_no, tok in body:
        where = f"line {line_no}"
        if len(tok) != _FIELDS:
            raise InputError(f"{where} has {len(tok)} fields, expected {_FIELDS} "
                             "(name k11..k33 r11..r33 t1 t2 t3)", path=par, fix=_PAR_FIX)
        try:
            vals = np.array([float(v) for v in tok[1:]], dtype=np.float64)
        except ValueError:
            raise InputError(f"{where}: a camera value is not a number", path=par, fix=_PAR_FIX) from None
        if not np.all(np.isfinite(vals)):
            raise InputError(f"{where}: a camera value is not finite", path=par, fix=_PAR_FIX)
        K, R, t = vals[:9].reshape(3, 3), vals[9:18].reshape(3, 3), vals[18:]
        if K[2, 2] == 0 or abs(K[2, 0]) > 0 or abs(K[2, 1]) > 0:
            raise InputError(f"{where}: K's last row must be (0, 0, k33) with k33 != 0", path=par, fix=_PAR_FIX)
        K = K / K[2, 2]
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or K[1, 0] != 0:
            raise InputError(f"{where}: K has skew ({K[0, 1]:g}), which a pinhole camera cannot hold", path=par,
                             fix=_PAR_FIX)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"{where}: focal lengths must be positive", path=par, fix=_PAR_FIX)
        R = rotation_checked(R, what=where, path=par)
        file = par.parent / tok[0]
        if not file.is_file():
            raise InputError(f"{where} names image {tok[0]!r}, which is missing", path=file,
                             fix=f"put the image beside {par.name} or remove its line (and update the count)")
        w, h = image_size_wh(file)
        camera = Camera.pinhole(K[0, 0], K[1, 1], K[0, 2] + PIXEL_OFFSET_PX, K[1, 2] + PIXEL_OFFSET_PX, w, h)
        cfw = np.eye(4)
        cfw[:3, :3], cfw[:3, 3] = R, t
        views.append(CaptureView(name=Path(tok[0]).stem, image_path=file, camera=camera, cam_from_world=cfw))
    notes = (f"Middlebury K [R | t] world-to-camera; principal point + {PIXEL_OFFSET_PX} px (file: pixel centres "
             "at integer coordinates)",)
    return Capture(kind="middlebury", source=par, views=views, notes=notes)
