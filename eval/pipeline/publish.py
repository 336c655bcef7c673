"""Stage `export` of `denoise-gs run`: the last round's scene in the forms users open.

Outputs (in OUT):

    scene.splat                 the Gaussians in antimatter15's .splat (web viewers, SuperSplat)
    view/index.html             offline browser viewer of the scene and its cameras (viser's client)
    cameras/working/            the final cameras at the working size (COLMAP text)
    cameras/input/              the same poses with intrinsics scaled to each input photo's size, under
                                the photos' file names

The input-resolution cameras let the poses be reused on the full-size photos: a pixel
quantity scales by `W_in / W_work` in x and `H_in / H_work` in y (`mvgeo.camera.Camera.scaled`).
A photo whose working image was turned a quarter counter-clockwise (`sizes.json` `turned: 1`, a portrait
photo among landscape ones) gets its camera turned back first (`turn_back`), so `cameras/input/` describes
the photo as it is.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from eval.pipeline.inputs import read_sizes
from eval.pipeline.stage import StageContext
from eval.pipeline.summaries import ExportSummary
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model

__all__ = ["EXPORT_CODE", "EXPORT_OUTPUTS", "export", "input_size_cameras", "turn_back"]

#: What the stage writes (relative to OUT).
EXPORT_OUTPUTS = ("scene.splat", "view", "cameras")
#: Packages the stage runs besides this module (their source digests enter its key; the rule and the
#: other stages' lists: `eval.pipeline.stage`, `eval.pipeline.stages.STAGE_CODE`).
EXPORT_CODE = ("eval.pipeline", "splat", "denoise", "mvgeo")


#: cam_a_from_cam_b of a quarter turn: image B = `np.rot90(A)` (counter-clockwise) of a pinhole image A.
#: A pixel (x_b, y_b) of B is (W_A - y_b, x_b) of A (corner convention), so x_a = f_y^B X_a / Z_a + W_A - c_y^B
#: and y_a = f_x^B Y_a / Z_a + c_x^B with X_a = -Y_b, Y_a = X_b, Z_a = Z_b.
_A_FROM_B_QUARTER = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def turn_back(camera: Camera, cam_from_world: np.ndarray) -> tuple[Camera, np.ndarray]:
    """The camera and pose of photo A from those of its working image B = `np.rot90(A)` (a quarter turn
    counter-clockwise): A's intrinsics swap the focal lengths and move the principal point, its pose turns
    about the optical axis (`_A_FROM_B_QUARTER`). Pinhole cameras only.

    Args:
        camera: B's camera; cam_from_world: (3, 4) B's pose.

    Returns:
        (A's PINHOLE camera, of size B's height x B's width; A's (3, 4) cam_from_world).

    Raises:
        InputError: a camera with lens distortion (its coefficients would have to be turned too).
    """
    if np.any(camera.dist != 0.0):
        raise InputError(f"cannot turn back a {camera.model} camera with lens distortion",
                         fix="re-run with a pinhole calibration (undistorted photos)")
    width_a, height_a = camera.height, camera.width
    cam_a = Camera.pinhole(camera.fy, camera.fx, width_a - camera.cy, camera.cx, width_a, height_a)
    return cam_a, _A_FROM_B_QUARTER @ np.asarray(cam_from_world, np.float64)[:3]


def input_size_cameras(sparse: SparseModel, sizes: Mapping[str, Mapping[str, object]]) -> SparseModel:
    """`sparse` (working-size cameras) with each image's camera scaled to its input size, and turned back
    where its working image was turned (`turn_back`; `sizes` as `read_sizes` returns them), named as its
    photo is in the input folder (`IMG_0001.JPG`, not the working `IMG_0001.png`) where `sizes` records it.

    Images that share a camera, an input size and a turn keep sharing one; an image whose input size
    or turn differs from its camera's other images gets its own camera (new id).

    Raises:
        InputError: an image of `sparse` missing from `sizes`, or a working size that does not
            match its camera.
    """
    cameras: dict[int, Camera] = {}
    new_id: dict[tuple[int, tuple[int, int], int], int] = {}
    images = []
    for im in sparse.images:
        stem = Path(im.name).stem
        if stem not in sizes:
            raise InputError(f"view {stem!r} has no recorded input size", fix="re-run with --force")
        cam = sparse.cameras[im.camera_id]
        if tuple(sizes[stem]["working"]) != (cam.width, cam.height):
            raise InputError(f"view {stem!r}: working size {sizes[stem]['working']} differs from its camera's "
                             f"{cam.width}x{cam.height}", fix="re-run with --force")
        turned = int(sizes[stem].get("turned", 0))
        cam_from_world = im.cam_from_world
        if turned:
            cam, cam_from_world = turn_back(cam, cam_from_world)
        key = (im.camera_id, tuple(sizes[stem]["input"]), turned)
        if key not in new_id:
            new_id[key] = im.camera_id if im.camera_id not in cameras else max([*cameras, *sparse.cameras]) + 1
            cameras[new_id[key]] = cam.scaled(*key[1])
        images.append(PosedImage(sizes[stem].get("file") or im.name, new_id[key], cam_from_world))
    return SparseModel(cameras, images, sparse.points_xyz, sparse.points_rgb)


def export(ctx: StageContext) -> Mapping[str, object]:
    """Write `scene.splat`, `view/` and `cameras/` for the scene `ctx.inputs["scene"]` (a 3DGS PLY), the
    cameras `ctx.inputs["sparse"]/0` and the sizes `ctx.inputs["sizes"]`; returns an `ExportSummary`'s JSON."""
    # splat loads torch: imported when the stage runs, not when this module is imported.
    from splat.export import write_splat
    from splat.ply import read_gaussian_ply
    from splat.viewer import viewer_page, write_view_folder

    model = read_gaussian_ply(ctx.inputs["scene"])
    sparse = read_sparse_model(Path(ctx.inputs["sparse"]) / "0")
    sizes = read_sizes(ctx.inputs["sizes"])
    work = ctx.work_dir
    write_splat(work / "scene.splat", model)
    (work / "view").mkdir()
    write_view_folder(work / "view", viewer_page(model, sparse))
    write_sparse_model(work / "cameras" / "working", sparse, binary=False)
    full = input_size_cameras(sparse, sizes)
    write_sparse_model(work / "cameras" / "input", full, binary=False)
    return ExportSummary(num_gaussians=model.num_gaussians, splat_bytes=(work / "scene.splat").stat().st_size,
                         working_size=sorted({f"{c.width}x{c.height}" for c in sparse.cameras.values()}),
                         input_size=sorted({f"{c.width}x{c.height}" for c in full.cameras.values()})).to_json()
