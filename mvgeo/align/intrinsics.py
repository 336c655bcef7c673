"""Known calibration for `mvgeo align --intrinsics`, and the focal length prior the photos' EXIF gives.

`read_intrinsics`: a COLMAP cameras.txt or an mrcal .cameramodel becomes a `mvgeo.camera.Camera` in our
pixel convention (mrcal's principal point is shifted by +0.5, docs/conventions.md). Images are
undistorted with OpenCV before the alignment, which then sees a PINHOLE camera with the same fx, fy, cx, cy.

`exif_focal_prior`: without a calibration, the 35 mm-equivalent focal length cameras write into EXIF
(FocalLengthIn35mmFilm) is the alignment's starting focal, as COLMAP's image reader uses it. A
35 mm-equivalent focal gives the same diagonal field of view on a 36 x 24 mm frame, so in pixels it is
``f35 * hypot(W, H) / hypot(36, 24)`` at any image size (resizing keeps it; cropping does not); exact
for 3:2 photos (``f35 * W / 36``); pycolmap 4's image reader computes the same prior from the same tag
(tests/common/test_exif_focal.py). The rule of thumb ``f35 / 35 * max(W, H)`` is 1.1 % under it for 4:3
photos and 2.8 % over it for 3:2 ones.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import exif_focal_35mm
from mvgeo.sparse_model import read_sparse_model

__all__ = ["FULL_FRAME_DIAGONAL_MM", "MAX_FOCAL_PER_SIDE", "FocalPrior", "check_camera", "choose_focal_prior",
           "common_focal_prior", "exif_focal_prior", "opencv_distortion", "read_intrinsics", "undistort_image"]

_log = logging.getLogger(__name__)

#: The diagonal of the 36 x 24 mm frame a 35 mm-equivalent focal length refers to.
FULL_FRAME_DIAGONAL_MM = float(np.hypot(36.0, 24.0))

_MRCAL_TO_COLMAP = {"LENSMODEL_PINHOLE": 0, "LENSMODEL_OPENCV4": 4, "LENSMODEL_OPENCV5": 5, "LENSMODEL_OPENCV8": 8}


def read_intrinsics(path: str | Path) -> Camera:
    """Read one camera from a COLMAP `cameras.txt` (exactly one camera) or an mrcal `.cameramodel`.

    Raises:
        InputError: missing/unreadable file, several cameras, an unsupported model, or a camera no lens has
            (`check_camera`).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("intrinsics file does not exist", path=path,
                         fix="pass a COLMAP cameras.txt or an mrcal .cameramodel")
    if path.suffix == ".cameramodel":
        return check_camera(_read_mrcal(path), path)
    if path.suffix == ".txt":
        return check_camera(_read_colmap_cameras_txt(path), path)
    raise InputError("unknown intrinsics format", path=path, fix="use a COLMAP cameras.txt or an mrcal .cameramodel")


#: The longest focal length `check_camera` accepts, in multiples of the image's long side: a field of view
#: of about 0.6 deg (a 1000 mm lens on an APS-C sensor is about 43).
MAX_FOCAL_PER_SIDE = 100.0


def check_camera(camera: Camera, path: str | Path) -> Camera:
    """`camera` as it is, if a lens can have it: finite parameters, focal lengths positive and at most
    `MAX_FOCAL_PER_SIDE` times the image's long side. Else an `InputError` naming `path` (a zero focal made
    the two-view geometry singular; a negative one passed and failed later as a divergence or a
    disconnected pair graph)."""
    if not np.all(np.isfinite(camera.params)):
        raise InputError(f"the camera's parameters are not all finite numbers: {camera.params.tolist()}", path=path,
                         fix="write the calibration's numbers (fx, fy, cx, cy, ...) in pixels")
    long_side = max(camera.width, camera.height)
    for name, f in (("fx", camera.fx), ("fy", camera.fy)):
        if not 0.0 < f <= MAX_FOCAL_PER_SIDE * long_side:
            raise InputError(f"focal length {name} = {f:g} px: it must be positive and at most "
                             f"{MAX_FOCAL_PER_SIDE:g} times the image's long side ({long_side} px)", path=path,
                             fix="write the focal length in pixels of the image size the file names "
                                 f"({camera.width}x{camera.height})")
    return camera


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
            raise InputError(f"cannot parse COLMAP cameras file: {exc.message}", path=path,
                             fix="write one camera line: CAMERA_ID MODEL WIDTH HEIGHT PARAMS... (COLMAP's "
                                 "cameras.txt)") from exc
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
        raise InputError(f"cannot read mrcal camera model: {exc}", path=path,
                         fix="give an mrcal .cameramodel file as mrcal writes it, or a COLMAP cameras.txt") from exc
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


@dataclass(frozen=True)
class FocalPrior:
    """A starting focal length for the alignment, as a 35 mm-equivalent (so it holds at any image size).

    Attributes:
        focal_35mm: millimetres on a 36 x 24 mm frame.
        source: where it comes from: "exif" (the photos' FocalLengthIn35mmFilm) or "given".
    """

    focal_35mm: float
    source: str = "given"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.focal_35mm) and self.focal_35mm > 0):
            raise ValueError(f"focal_35mm must be a positive number of millimetres, got {self.focal_35mm}")

    def focal_px(self, size_wh: tuple[int, int]) -> float:
        """The focal length in pixels of an image of `size_wh` (W, H): the same diagonal field of view."""
        return float(self.focal_35mm * np.hypot(*size_wh) / FULL_FRAME_DIAGONAL_MM)


def exif_focal_prior(paths: Sequence[str | Path], *, max_rel_spread: float = 0.01) -> tuple[FocalPrior | None, str]:
    """The photos' common EXIF 35 mm-equivalent focal length, or (None, why not) (`common_focal_prior`)."""
    return common_focal_prior([exif_focal_35mm(p) for p in paths], [Path(p).name for p in paths],
                              max_rel_spread=max_rel_spread)


def common_focal_prior(focal_35mm: Sequence[float | None], names: Sequence[str], *, max_rel_spread: float = 0.01
                       ) -> tuple[FocalPrior | None, str]:
    """One EXIF focal prior from the photos' 35 mm-equivalent focal lengths (None: the photo has none), or
    (None, why not).

    The alignment assumes one camera: the prior is given only when every photo carries one and the values
    agree within `max_rel_spread` of their median (a zoom that changed between photos, or photos from
    several cameras, give none). Photos without EXIF (PNG exports, the benchmark sets) give none.
    """
    if not len(focal_35mm):
        return None, "no photos"
    missing = [n for n, v in zip(names, focal_35mm, strict=True) if v is None]
    if missing:
        why = (f"{len(missing)} of {len(focal_35mm)} photos have no EXIF 35 mm-equivalent focal length"
               + (f" (e.g. {missing[0]})" if len(missing) < len(focal_35mm) else ""))
        return None, why
    f = np.asarray(focal_35mm, np.float64)
    med = float(np.median(f))
    if np.max(np.abs(f / med - 1.0)) > max_rel_spread:
        why = (f"the photos' EXIF 35 mm-equivalent focal lengths differ ({f.min():g}-{f.max():g} mm: a zoom "
               "that changed between photos, or several cameras); one shared focal is estimated instead")
        _log.warning("no focal prior from EXIF: %s", why)
        return None, why
    return FocalPrior(med, "exif"), ""


def choose_focal_prior(images: Sequence, *, known_intrinsics: bool, given: FocalPrior | None, read_exif: bool
                       ) -> tuple[FocalPrior | None, str]:
    """The focal prior `mvgeo.align.align_images` starts its pairs at, or (None, why not): none with known
    intrinsics; `given` when given; else the image files' common EXIF focal (`exif_focal_prior`) when
    `read_exif` (`AlignConfig.exif_focal`) and the images are files."""
    if known_intrinsics:
        return None, "the intrinsics are known"
    if given is not None:
        return given, ""
    if not read_exif:
        return None, "EXIF focal lengths not read (AlignConfig.exif_focal off)"
    if not all(isinstance(x, (str, Path)) for x in images):
        return None, "the images were given as arrays (no EXIF)"
    return exif_focal_prior(list(images))
