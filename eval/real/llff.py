"""LLFF captures: `poses_bounds.npy` plus `images/` or `images_N/`.

File format (LLFF's `imgs2poses.py`, read by NeRF's `load_llff_data`): an
(N, 17) float array, one row per image in sorted file-name order. The first 15
values reshape (row-major) to a 3 x 5 matrix ``[c0 c1 c2 | C | hwf]``:

- ``c0, c1, c2``: the camera's *down*, *right* and *back* axes expressed in
  world coordinates (the columns of a camera-to-world rotation in LLFF's
  (down, right, back) axis order; the camera looks along -back);
- ``C``: the camera centre in world coordinates;
- ``hwf = (H, W, f)``: height, width and focal length in pixels of the
  full-size images (`images/`).

The last two values are the near and far z-depth bounds of the scene points
COLMAP saw in that view.

Conversion to ours (OpenCV axes: x right, y down, z forward). Our camera's
axes in world coordinates are x = right = c1, y = down = c0, z = forward =
-back = -c2, so

    world_from_cam = [[c1, c0, -c2, C], [0, 0, 0, 1]],
    cam_from_world = [[R^T, -R^T C], [0, 0, 0, 1]] with R = [c1 c0 -c2].

(down, right, back) is right-handed (down x right = back), and so is the
result (det R = +1; checked). NeRF's loader instead reorders to OpenGL's
(right, up, back) = (c1, -c0, c2) and projects with
``u = W/2 + f x / (-z)``, ``v = H/2 - f y / (-z)``; our matrix gives the same
pixels (tests/eval/test_real_import.py projects a scene both ways).

Intrinsics: LLFF keeps no principal point; COLMAP, which LLFF ran, fixed it at
the image centre, which is ``(W/2, H/2)`` in our pixel convention (image
spanning [0, W], as COLMAP's). So for images of w x h (e.g. `images_4/`):
``fx = f w / W``, ``fy = f h / H``, ``cx = w / 2``, ``cy = h / 2``, exact
under our convention whatever the rounding of the downsampled size. (NeRF's
original ray generation uses ``(i - W/2)`` for integer pixel index ``i``,
i.e. rays through pixel corners, a known half-pixel slip; we follow COLMAP.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eval.real.capture import Capture, CaptureView, image_size_wh, rotation_checked
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import list_images
from mvgeo.common.npyio import load_numpy

__all__ = ["cam_from_world_from_llff", "read_llff"]


def cam_from_world_from_llff(pose_3x5: np.ndarray, *, what: str = "pose", path: Path = Path("poses_bounds.npy")
                             ) -> np.ndarray:
    """(4, 4) `cam_from_world` (OpenCV axes) from one LLFF (3, 5) ``[down right back | C | hwf]`` matrix.

    Raises:
        InputError: the 3 x 3 block is not a rotation.
    """
    p = np.asarray(pose_3x5, dtype=np.float64)
    R_world_from_cam = np.stack([p[:, 1], p[:, 0], -p[:, 2]], axis=1)
    R_world_from_cam = rotation_checked(R_world_from_cam, what=what, path=path, tol=1e-4)
    C = p[:, 3]
    out = np.eye(4)
    out[:3, :3] = R_world_from_cam.T
    out[:3, 3] = -R_world_from_cam.T @ C
    return out


def read_llff(src: str | Path, *, factor: int | None = None) -> Capture:
    """Read an LLFF capture folder.

    Args:
        src: folder with `poses_bounds.npy` and `images/` (full size) or `images_<factor>/`.
        factor: read `images_<factor>/` (LLFF's downsampled copies); None reads `images/`.

    Returns:
        The capture; views in sorted file-name order, `near_far` from the file.

    Raises:
        InputError: missing folder/file, an array that is not (N, 17), a row count that differs from the
            image count, images whose size does not match the file's (H, W) and `factor`, non-rotations.
    """
    src = Path(src)
    if not src.is_dir():
        raise InputError("LLFF folder does not exist", path=src)
    npy = src / "poses_bounds.npy"
    if not npy.is_file():
        raise InputError("not an LLFF capture: no poses_bounds.npy", path=npy,
                         fix="point at the scene folder holding poses_bounds.npy and images/ (LLFF's imgs2poses.py)")
    arr = load_numpy(npy, fix="restore poses_bounds.npy (LLFF's imgs2poses.py writes it: an (N, 17) array)")
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] < 1 or not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"poses_bounds.npy must be an (N, 17) number array, got shape {arr.shape} "
                         f"dtype {arr.dtype}", path=npy,
                         fix="each row is a 3x5 [down right back | centre | hwf] matrix, row-major, then near, far")
    if factor is not None and factor < 1:
        raise InputError(f"the LLFF image factor must be >= 1, got {factor}")
    folder = src / ("images" if factor is None else f"images_{factor}")
    if factor is not None and not folder.is_dir():
        have = sorted(p.name for p in src.glob("images_*") if p.is_dir())
        raise InputError(f"--factor {factor} reads {folder.name}/, which this capture does not have", path=folder,
                         fix=(f"pass --factor with one of its folders ({', '.join(have)}), or " if have else "")
                         + "leave --factor out to import images/")
    files = list_images(folder)
    if len(files) != len(arr):
        raise InputError(f"poses_bounds.npy has {len(arr)} rows but {folder.name}/ holds {len(files)} images",
                         path=folder, fix="the rows follow the sorted image names one to one: keep exactly the "
                                          "images the poses were computed for")
    views = []
    for i, (row, file) in enumerate(zip(arr.astype(np.float64), files, strict=True)):
        what = f"row {i} ({file.name})"
        if not np.all(np.isfinite(row)):
            raise InputError(f"{what} holds a non-finite value", path=npy,
                             fix="write poses_bounds.npy again (LLFF's imgs2poses.py, or COLMAP's poses)")
        pose = row[:15].reshape(3, 5)
        H, W, f = pose[:, 4]
        if H <= 0 or W <= 0 or f <= 0:
            raise InputError(f"{what}: hwf must be positive, got H={H:g} W={W:g} f={f:g}", path=npy,
                             fix="write poses_bounds.npy again: each row is a 3x5 [R | t | (H, W, f)] and near, far")
        w, h = image_size_wh(file)
        if factor is not None and (abs(w - W / factor) > 1.0 or abs(h - H / factor) > 1.0):
            raise InputError(f"{file.name} is {w}x{h}, but the poses' full size {W:g}x{H:g} / {factor} is "
                             f"{W / factor:g}x{H / factor:g}", path=file,
                             fix=f"images_{factor}/ must hold the images downsampled {factor} times")
        if abs(w * H - h * W) > max(W, H):
            raise InputError(f"{file.name} is {w}x{h}, a different aspect from the poses' {W:g}x{H:g}", path=file,
                             fix="the images must be the photographs the poses were computed for (or resized "
                                 "copies of them)")
        camera = Camera.pinhole(f * w / W, f * h / H, w / 2.0, h / 2.0, w, h)
        near, far = float(row[15]), float(row[16])
        views.append(CaptureView(name=file.stem, image_path=file, camera=camera,
                                 cam_from_world=cam_from_world_from_llff(pose, what=what, path=npy),
                                 near_far=(near, far) if 0 < near < far else None))
    notes = ("LLFF (down, right, back) camera-to-world columns c0 c1 c2 -> world_from_cam rotation [c1 c0 -c2]",
             "principal point at the image centre (w/2, h/2) in our pixel convention; f scaled by w/W, h/H")
    return Capture(kind="llff", source=src, views=views, notes=notes)
