"""Known calibration for `mvgeo align --intrinsics`: COLMAP cameras.txt or mrcal .cameramodel.

Both become a `mvgeo.camera.Camera` in our pixel convention (mrcal's
principal point is shifted by +0.5, docs/conventions.md). Images are
undistorted with OpenCV before the alignment, which then sees a PINHOLE camera
with the same fx, fy, cx, cy.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.sparse_model import read_sparse_model

_MRCAL_TO_COLMAP = {"LENSMODEL_PINHOLE": 0, "LENSMODEL_OPENCV4": 4, "LENSMODEL_OPENCV5": 5, "LENSMODEL_OPENCV8": 8}


def read_intrinsics(path: str | Path) -> Camera:
    """Read one camera from a COLMAP `cameras.txt` (exactly one camera) or an mrcal `.cameramodel`.

    Raises:
        InputError: missing/unreadable file, several cameras, or an unsupported model.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("intrinsics file does not exist", path=path,
                         fix="pass a COLMAP cameras.txt or an mrcal .cameramodel")
    if path.suffix == ".cameramodel":
        return _read_mrcal(path)
    if path.suffix == ".txt":
        return _read_colmap_cameras_txt(path)
    raise InputError("unknown intrinsics format", path=path, fix="use a COLMAP cameras.txt or an mrcal .cameramodel")


def _read_colmap_cameras_txt(path: Path) -> Camera:
    # Parse through the project's one COLMAP reader: a model folder with empty images/points3D.
    tmp = Path(tempfile.mkdtemp(prefix="intrinsics-"))
    try:
        shutil.copy(path, tmp / "cameras.txt")
        (tmp / "images.txt").write_text("")
        (tmp / "points3D.txt").write_text("")
        try:
            cams = read_sparse_model(tmp).cameras
        except InputError as exc:
            raise InputError(f"cannot parse COLMAP cameras file: {exc.message}", path=path) from exc
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if len(cams) != 1:
        raise InputError(f"expected exactly one camera, found {len(cams)}", path=path,
                         fix="keep only the camera of these images in the file")
    return next(iter(cams.values()))


def _read_mrcal(path: Path) -> Camera:
    import mrcal

    try:
        model = mrcal.cameramodel(str(path))
    except Exception as exc:  # mrcal raises plain exceptions on bad files
        raise InputError(f"cannot read mrcal camera model: {exc}", path=path) from exc
    lensmodel, p = model.intrinsics()
    if lensmodel not in _MRCAL_TO_COLMAP:
        raise InputError(f"unsupported mrcal lens model {lensmodel}", path=path,
                         fix="use LENSMODEL_PINHOLE or LENSMODEL_OPENCV4/5/8")
    W, H = (int(x) for x in model.imagersize())
    fx, fy, cx, cy = p[:4]
    cx, cy = cx + 0.5, cy + 0.5  # mrcal: top-left pixel centre at (0, 0); ours (0.5, 0.5)
    dist = np.zeros(8)
    dist[: len(p) - 4] = p[4:]
    if not np.any(dist):
        return Camera.pinhole(fx, fy, cx, cy, W, H)
    return Camera("FULL_OPENCV", W, H, np.concatenate([[fx, fy, cx, cy], dist]))


def opencv_distortion(camera: Camera) -> np.ndarray:
    """(8,) OpenCV distortion vector `k1 k2 p1 p2 k3 k4 k5 k6` of a camera (zeros for pinhole models)."""
    p = camera.params
    dist = np.zeros(8)
    if camera.model == "SIMPLE_RADIAL":
        dist[0] = p[3]
    elif camera.model in ("OPENCV", "FULL_OPENCV"):
        dist[: len(p) - 4] = p[4:]
    return dist


def undistort_image(image: np.ndarray, camera: Camera) -> np.ndarray:
    """Remove lens distortion; the result is a PINHOLE image with `camera.K` (same size).

    Args:
        image: (H, W, 3) float32, H and W equal to the camera's size.
    """
    dist = opencv_distortion(camera)
    if not np.any(dist):
        return image
    K_cv = camera.K.copy()
    K_cv[0, 2] -= 0.5  # OpenCV pixel centres at integers
    K_cv[1, 2] -= 0.5
    return cv2.undistort(image, K_cv, dist, None, K_cv)
