"""COLMAP captures: a model folder (`sparse/0`, binary or text) plus its images.

COLMAP's conventions are the project's (OpenCV axes, `cam_from_world`, the
top-left pixel's centre at (0.5, 0.5)), so nothing is converted: the model is
read through `mvgeo.sparse_model` (pycolmap) and the cameras keep their model
(distortion included). Only registered images are views; the model's 3-D
points are carried over (without tracks).
"""

from __future__ import annotations

from pathlib import Path

from eval.real.capture import Capture, CaptureView, image_size_wh
from mvgeo.common.errors import InputError
from mvgeo.sparse_model import read_sparse_model

__all__ = ["read_colmap"]


def read_colmap(src: str | Path, *, model_dir: str | Path | None = None, images_dir: str | Path | None = None
                ) -> Capture:
    """Read a COLMAP capture folder.

    Args:
        src: the project folder (holding `sparse/0/` and `images/` unless given below).
        model_dir: the model folder; default `src/sparse/0`.
        images_dir: the folder the model's image names are relative to; default `src/images`.

    Returns:
        The capture; views sorted by image name, world units unknown.

    Raises:
        InputError: a missing or unreadable model, an image the model names that is missing, or an image
            whose size differs from its camera's.
    """
    src = Path(src)
    if not src.is_dir():
        raise InputError("COLMAP project folder does not exist", path=src,
                         fix="give the folder that holds sparse/0/ (or sparse/) and images/")
    model_dir = src / "sparse" / "0" if model_dir is None else Path(model_dir)
    images_dir = src / "images" if images_dir is None else Path(images_dir)
    model = read_sparse_model(model_dir)
    if not model.images:
        raise InputError("the COLMAP model has no registered images", path=model_dir)
    if not images_dir.is_dir():
        raise InputError("images folder does not exist", path=images_dir,
                         fix="pass the folder the model's image names are relative to")
    views = []
    for im in model.images:
        file = images_dir / im.name
        if not file.is_file():
            raise InputError(f"the model's image {im.name!r} is missing", path=file,
                             fix=f"put the image in {images_dir} or point at the right images folder")
        cam = model.cameras[im.camera_id]
        w, h = image_size_wh(file)
        if (w, h) != (cam.width, cam.height):
            raise InputError(f"{im.name} is {w}x{h} but its camera {im.camera_id} is {cam.width}x{cam.height}",
                             path=file, fix="use the images the model was reconstructed from (same size)")
        name = str(Path(im.name).with_suffix("")).replace("/", "_").replace("\\", "_")
        views.append(CaptureView(name=name, image_path=file, camera=cam, cam_from_world=im.cam_from_world))
    return Capture(kind="colmap", source=src, views=views, notes=("COLMAP conventions are ours: no conversion",),
                   points_xyz=model.points_xyz, points_rgb=model.points_rgb)
