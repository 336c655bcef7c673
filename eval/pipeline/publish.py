"""Stage `export` of `denoise-gs run`: the last round's scene in the forms users open.

Outputs (in OUT):

    scene.splat                 the Gaussians in antimatter15's .splat (web viewers, SuperSplat)
    view/index.html             offline browser viewer of the scene and its cameras (viser's client)
    cameras/working/            the final cameras at the working size (COLMAP text)
    cameras/input/              the same poses with intrinsics scaled to each input photo's size

The input-resolution cameras let the poses be reused on the full-size photos: a pixel
quantity scales by `W_in / W_work` in x and `H_in / H_work` in y (`mvgeo.camera.Camera.scaled`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from eval.pipeline.inputs import read_sizes
from eval.pipeline.stage import StageContext
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model

__all__ = ["EXPORT_CODE", "EXPORT_OUTPUTS", "export", "input_size_cameras"]

#: What the stage writes (relative to OUT).
EXPORT_OUTPUTS = ("scene.splat", "view", "cameras")
#: Packages the stage runs besides this module (their source digests enter its key; the rule and the
#: other stages' lists: `eval.pipeline.stage`, `eval.pipeline.stages.STAGE_CODE`).
EXPORT_CODE = ("eval.pipeline", "splat", "denoise", "mvgeo")


def input_size_cameras(sparse: SparseModel, sizes: Mapping[str, Mapping[str, tuple[int, int]]]) -> SparseModel:
    """`sparse` (working-size cameras) with each image's camera scaled to its input size.

    Images that share a camera and an input size keep sharing one; an image whose input size
    differs from its camera's other images gets its own camera (new id).

    Raises:
        InputError: an image of `sparse` missing from `sizes`, or a working size that does not
            match its camera.
    """
    cameras: dict[int, Camera] = {}
    new_id: dict[tuple[int, tuple[int, int]], int] = {}
    images = []
    for im in sparse.images:
        stem = Path(im.name).stem
        if stem not in sizes:
            raise InputError(f"view {stem!r} has no recorded input size", fix="re-run with --force")
        cam = sparse.cameras[im.camera_id]
        if tuple(sizes[stem]["working"]) != (cam.width, cam.height):
            raise InputError(f"view {stem!r}: working size {sizes[stem]['working']} differs from its camera's "
                             f"{cam.width}x{cam.height}", fix="re-run with --force")
        key = (im.camera_id, tuple(sizes[stem]["input"]))
        if key not in new_id:
            new_id[key] = im.camera_id if im.camera_id not in cameras else max([*cameras, *sparse.cameras]) + 1
            cameras[new_id[key]] = cam.scaled(*key[1])
        images.append(PosedImage(im.name, new_id[key], im.cam_from_world))
    return SparseModel(cameras, images, sparse.points_xyz, sparse.points_rgb)


def export(ctx: StageContext) -> Mapping[str, object]:
    """Write `scene.splat`, `view/` and `cameras/` for the scene `ctx.inputs["scene"]` (a 3DGS PLY), the
    cameras `ctx.inputs["sparse"]/0` and the sizes `ctx.inputs["sizes"]`."""
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
    return {"num_gaussians": model.num_gaussians, "splat_bytes": (work / "scene.splat").stat().st_size,
            "working_size": sorted({f"{c.width}x{c.height}" for c in sparse.cameras.values()}),
            "input_size": sorted({f"{c.width}x{c.height}" for c in full.cameras.values()})}
