"""Stage functions of the evaluation's baselines (`eval.methods`), with the pipeline's stage signature.

- `identity_denoise`, `nlm_denoise`, `oracle_clean_denoise`: round 1's denoise stage of
  `instantsplat` (none), `nlm_instantsplat` (non-local means) and `oracle_clean` (the clean
  photos). None of them has a network, so each writes `denoised/` alone (the pipeline's
  `PipelineStages.denoise_outputs` says so) and runs round 1 only.
- `gt_align`: the ground-truth cameras of the training views and initial points, written as the
  align stage writes its folder, so that `3dgs_gt_poses` trains with the pipeline's own splat stage.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from denoise.noise_level import estimate_noise_sigma
from eval.pipeline.stage import StageContext
from eval.pipeline.summaries import AlignSummary, DenoiseSummary
from eval.pipeline.validate import DatasetFolder
from eval.pipeline.views import read_views, view_files, write_views
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import SparseModel, read_sparse_model, write_sparse_model

__all__ = ["CLASSICAL_DENOISE_OUTPUTS", "GtAlignSettings", "gt_align", "identity_denoise", "nlm_denoise",
           "oracle_clean_denoise"]

#: What the classical denoise stages write (no network: no `n2v_model.pt`).
CLASSICAL_DENOISE_OUTPUTS = ("denoised",)


def identity_denoise(ctx: StageContext) -> Mapping[str, object]:
    """(b): no denoising; the noisy images go to alignment and splatting as they are."""
    write_views(ctx.work_dir / "denoised", read_views(ctx.inputs["noisy"]))
    return DenoiseSummary(denoiser="none").to_json()


def nlm_denoise(ctx: StageContext) -> Mapping[str, object]:
    """(c): scikit-image non-local means, h = 0.8 sigma (its documented recipe), sigma estimated per image."""
    from skimage.restoration import denoise_nl_means  # scikit-image: a second to import, this stage only

    out, sigmas = {}, {}
    for name, img in read_views(ctx.inputs["noisy"]).items():
        sigma = estimate_noise_sigma(img)
        out[name] = denoise_nl_means(img, h=0.8 * sigma, sigma=sigma, fast_mode=True, patch_size=5,
                                     patch_distance=6, channel_axis=-1).astype(np.float32)
        sigmas[name] = sigma
    write_views(ctx.work_dir / "denoised", out)
    return DenoiseSummary(denoiser="skimage.denoise_nl_means", sigma_est=sigmas).to_json()


def oracle_clean_denoise(ctx: StageContext) -> Mapping[str, object]:
    """`oracle_clean`: a perfect denoiser. The clean training photos (`ctx.inputs["clean"]`, the dataset's
    `clean/`, whose content enters the stage's key: `PipelineStages.denoise_inputs`) go to alignment and
    splatting.

    It reads `clean/` of the training views, so it is not a method a user could run: it is the
    ceiling of every denoise-then-reconstruct method on the scene with these settings (what the
    alignment and the splat lose on noise-free photos), against which the denoisers' gains are read.

    Raises:
        InputError: a training view without a clean image.
    """
    noisy = read_views(ctx.inputs["noisy"])
    clean_files = view_files(ctx.inputs["clean"])
    missing = [n for n in noisy if n not in clean_files]
    if missing:
        raise InputError(f"oracle_clean: no clean image for {missing}", fix="use a dataset with clean/ for every view")
    write_views(ctx.work_dir / "denoised", {n: read_image(clean_files[n]) for n in noisy})
    return DenoiseSummary(denoiser="oracle (clean photos)").to_json()


@dataclass(frozen=True)
class GtAlignSettings:
    """Settings of `gt_align`. Attributes: views: stems of the training views."""

    views: tuple[str, ...]


def gt_align_inputs(dataset: DatasetFolder, estimate: Path | None = None) -> dict[str, Path]:
    """The files `gt_align` reads (all of them enter its key by content): the dataset's, and with
    `estimate` (a pipeline round folder) that round's cameras and alignment points instead of depth maps."""
    inputs = {"sparse": dataset.root / "sparse" / "0", "images": dataset.root / "images",
              "split": dataset.root / "split.json"}
    if estimate is not None:
        inputs["estimate_sparse"] = Path(estimate) / "sparse" / "0"
        inputs["estimate_points"] = Path(estimate) / "align" / "points.npz"
    elif (dataset.root / "depth").is_dir():
        inputs["depth"] = dataset.root / "depth"
    return inputs


def points_in_reference_frame(estimate_sparse: Path, estimate_points: Path, reference: SparseModel,
                              views: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """A reconstruction's alignment points (`points.npz`: xyz, rgb) placed in the reference (ground-truth)
    frame along the reference cameras' rays. Returns (xyz (M, 3) float64, rgb (M, 3) uint8), M <= N.

    Each point is seen by the reconstruction's own camera of the nearest view that sees it (in front,
    inside the image) at a pixel and a depth; it goes on the reference camera's ray through that pixel
    of that view, at that depth divided by the scale of the Sim(3) that registers the reconstruction's
    cameras `views` to the reference ones (`eval.heldout.register_sim3`). So a point lands where the
    true camera sees the image content the reconstruction put there, whatever the reconstruction's pose
    and focal errors; only its depth keeps the reconstruction's error. (A single Sim(3) applied to the
    points does not: a reconstruction with a focal a few percent off is distorted, and its points moved
    by one similarity miss their pixels under the true cameras.) Points no view sees are dropped.
    """
    from eval.heldout import register_sim3

    est = read_sparse_model(estimate_sparse)
    by_stem = {Path(n).stem: n for n in est.names}
    ref_by_stem = {Path(n).stem: n for n in reference.names}
    used = [v for v in views if v in by_stem and v in ref_by_stem]
    est_from_ref, _ = register_sim3({v: est.image(by_stem[v]).cam_from_world for v in used},
                                    {v: reference.image(ref_by_stem[v]).cam_from_world for v in used})
    with np.load(estimate_points) as z:
        xyz, rgb = np.asarray(z["xyz"], np.float64), np.asarray(z["rgb"], np.uint8)
    best_depth = np.full(len(xyz), np.inf)
    best_xyz = np.zeros_like(xyz)
    for v in used:
        cam_e, cfw_e = est.camera_of(by_stem[v]), np.asarray(est.image(by_stem[v]).cam_from_world)[:3]
        ref_name = ref_by_stem[v]
        cam_r, cfw_r = reference.camera_of(ref_name), np.asarray(reference.image(ref_name).cam_from_world)[:3]
        p_cam = xyz @ cfw_e[:, :3].T + cfw_e[:, 3]
        proj = cam_e.project(p_cam)
        # pixel -> the reference image's pixel (same image; sizes may differ by a resize)
        uv = proj.uv_px * [cam_r.width / cam_e.width, cam_r.height / cam_e.height]
        rays = cam_r.unproject(uv)
        seen = proj.valid & cam_e.in_image(proj.uv_px) & rays.valid & (p_cam[:, 2] > 0)
        closer = seen & (p_cam[:, 2] < best_depth)
        z_ref = p_cam[closer, 2] / est_from_ref.scale
        x_cam = rays.rays_cam[closer] * z_ref[:, None]
        best_xyz[closer] = (x_cam - cfw_r[:, 3]) @ cfw_r[:, :3]  # world = R^T (x_cam - t)
        best_depth[closer] = p_cam[closer, 2]
    keep = np.isfinite(best_depth)
    return best_xyz[keep], rgb[keep]


def gt_align(dataset: DatasetFolder, ctx: StageContext) -> Mapping[str, object]:
    """`align/` of (a) `3dgs_gt_poses` and the `@gt_poses` variants: `sparse/0` with the ground-truth
    cameras of the training views (`ctx.settings`: `GtAlignSettings`) and `points.npz` with the initial
    points: for a variant (inputs `estimate_sparse`, `estimate_points`), the alignment points of its
    points' method (`EvalMethod.gt_pose_points_from`) placed on the ground-truth cameras' rays
    (`points_in_reference_frame`); for (a), back-projected
    ground-truth depth maps when the dataset ships `depth/` (an oracle initialisation, so the baseline
    is optimistic), else the ground-truth model's points.

    Raises:
        InputError: no depth maps and no points in the ground-truth model.
    """
    from splat.dataset import load_views, points_from_depth  # torch: this stage only

    gt = read_sparse_model(ctx.inputs["sparse"])
    by_stem = {Path(n).stem: n for n in gt.names}
    images = [gt.image(by_stem[s]) for s in ctx.settings.views]
    source = "ground truth"
    if "estimate_points" in ctx.inputs:
        xyz, rgb = points_in_reference_frame(ctx.inputs["estimate_sparse"], ctx.inputs["estimate_points"], gt,
                                             ctx.settings.views)
        source = "another reconstruction's alignment, on the true cameras' rays"
    elif "depth" in ctx.inputs:
        xyz, rgb = points_from_depth(dataset.root, load_views(dataset.root, split="train"))
    elif len(gt.points_xyz):
        xyz, rgb = gt.points_xyz, gt.points_rgb
    else:
        raise InputError("3dgs_gt_poses needs initial points: no depth/ maps and no points in sparse/0",
                         path=dataset.root, fix="use a data_synth dataset (it ships depth/) or a model with points")
    out = ctx.work_dir / "align"
    cameras = {im.camera_id: gt.cameras[im.camera_id] for im in images}
    # The points go to points.npz (what the splat stage initialises from), not into the model.
    write_sparse_model(out / "sparse" / "0", SparseModel(cameras, images), binary=True)
    np.savez(out / "points.npz", xyz=np.asarray(xyz, np.float64), rgb=np.asarray(rgb, np.uint8),
             conf=np.ones(len(xyz)))
    return AlignSummary(registered=len(images), points=int(len(xyz)), poses="ground truth",
                        points_from=source).to_json()
