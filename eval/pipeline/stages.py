"""The product's stage functions: Denoise-GS's steps as disk-in, disk-out functions.

Each function has the `StageFn` signature (`fn(ctx) -> summary`), reads
`ctx.inputs`, writes the outputs `eval.pipeline.run` declares for it into
`ctx.work_dir`, and runs the component packages with the typed settings it
receives (`ctx.settings`, `eval.pipeline.stage_settings`).

The component packages (`denoise`, `splat`, `mvgeo.align`) load torch, so each
function imports what it calls when it runs, not when this module is imported.

| stage     | inputs                                   | outputs                                   |
|-----------|------------------------------------------|-------------------------------------------|
| denoise   | noisy                                    | denoised/, n2v_model.pt                   |
| align     | images [, previous_align (rounds >= 2)]  | align/ (sparse/0/, points.ply/.npz, json) |
| fuse      | noisy, images, align [, previous_*]      | fused/, noisy_renders/                    |
| splat     | images (or fused), align                 | sparse/0/, point_cloud.ply                |
| render    | sparse, scene                            | renders/                                  |
| select    | images, sparse                           | selection.json                            |
| refine    | noisy, selection, model, renders, previous | denoised/, n2v_model.pt                 |
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from denoise.detail import NoisyDetail, noisy_detail_target, noisy_detail_weight  # numpy and cv2 only
from eval.pipeline.align_decisions import (
    AlignDecisions,
    AlignStageResult,
    FocalEstimate,
    GeometryChoice,
    InheritedCalibration,
    PhotosDecision,
)
from eval.pipeline.calibration import (
    better_determined,
    choose_geometry,
    focal_log_std,
    prefer_previous,
    previous_calibration,
    restricted_ratios,
)
from eval.pipeline.hashing import file_sha256
from eval.pipeline.inputs import working_focal_prior
from eval.pipeline.stage import StageContext, StageFn
from eval.pipeline.stage_settings import FuseStageSettings, SplatStageSettings
from eval.pipeline.summaries import (
    DenoiseSummary,
    FuseSummary,
    NoisyDetailRecord,
    RecordedGeometryChoice,
    RefineSummary,
    SelectSummary,
    SplatSummary,
    history_ends,
)
from eval.pipeline.views import read_views, view_files, write_views
from mvgeo.align.stats import AlignStats
from mvgeo.camera import Camera
from mvgeo.common.errors import AlignmentRefusedError, DegenerateGeometryError, DisconnectedViewsError
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model

__all__ = ["DENOISE_OUTPUTS", "FUSE_WEIGHT", "MODEL_FILE", "ROTATION_ATOL", "STAGE_CODE",
           "NoisySplatReuse", "PipelineStages", "align", "as_pipeline_refusal", "denoise", "fuse", "fuse_images",
           "noisy_splat_reuse", "product_stages", "refine", "render", "select", "splat"]

_log = logging.getLogger(__name__)

#: The network a denoise or refine stage writes (round r >= 2 fine-tunes round r-1's).
MODEL_FILE = "n2v_model.pt"
#: What the product's denoise stage writes; a denoiser without a network (the evaluation's
#: baselines) writes "denoised" alone and runs round 1 only.
DENOISE_OUTPUTS = ("denoised", MODEL_FILE)


@dataclass(frozen=True)
class PipelineStages:
    """The stage functions `run_pipeline` calls; tests pass small real ones."""

    denoise: StageFn
    align: StageFn
    splat: StageFn
    render: StageFn
    select: StageFn
    refine: StageFn
    fuse: StageFn | None = None  # `PipelineConfig.fuse_noisy_splat`; required only when that is on
    #: OUT/scene.splat, view/, cameras/ from the last round (`eval.pipeline.publish`); None skips it.
    export: StageFn | None = None
    #: stage name -> modules/packages it runs besides its function's own module (`StageSpec.code`).
    code: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    #: What `denoise` writes into the round folder: `DENOISE_OUTPUTS`, or ("denoised",) for a
    #: denoiser without a network, which cannot start a round 2 (no `MODEL_FILE` to fine-tune).
    denoise_outputs: tuple[str, ...] = DENOISE_OUTPUTS


def denoise(ctx: StageContext) -> Mapping[str, object]:
    """Round 1: train the UNet on all noisy images with `n2v.method` (with `choose_objective`, the one
    `denoise.self_supervised.choose_objective` picks for them, recorded in the summary as `objective`),
    denoise them all (`ctx.settings`: `DenoiseStageSettings`); with `keep_noisy` k, `denoised/` holds
    ``(1 - k) * network output + k * noisy photo``. Where the photos' noise is correlated between
    neighbouring pixels (`pd_stride` 0: `denoise.pixel_shuffle.choose_stride` measures it) all of this runs
    on their pixel-shuffled sub-images, put back together after (`denoise.pixel_shuffle`). Returns a
    `DenoiseSummary`'s JSON."""
    from denoise.model import save_checkpoint
    from denoise.pixel_shuffle import merge_std, shuffled, stride_for, unshuffled
    from denoise.self_supervised import choose_objective
    from eval.pipeline.quality import noise_levels

    s = ctx.settings
    noisy = read_views(ctx.inputs["noisy"])
    photos = list(noisy.values())
    n2v, objective, dark_clipped_fraction = s.n2v, None, None
    if s.choose_objective:  # on the whole photos: the dark fraction's blur is in pixels of the photo
        choice = choose_objective(photos)
        n2v = dataclasses.replace(n2v, method=choice.method)
        objective, dark_clipped_fraction = choice.method, round(choice.dark_clipped_fraction, 4)
    levels = stride_for(photos, s.pd_stride)
    stride = levels.stride
    if stride > 1:
        _log.info("the photos' noise is correlated between neighbouring pixels (its level /255 by stride: %s): "
                  "denoising their %d x %d pixel-shuffled sub-images",
                  levels.levels_255(), stride, stride)
        photos = shuffled(photos, stride)
    out, stds, model = _denoise_photos(photos, n2v, s, ctx.seed)
    if stride > 1:
        n = stride * stride
        out = unshuffled(out, stride, [im.shape for im in noisy.values()])
        stds = [merge_std(stds[i * n:(i + 1) * n], stride, im.shape) for i, im in enumerate(noisy.values())]
    if s.keep_noisy > 0:
        out = [(1.0 - s.keep_noisy) * d + s.keep_noisy * y for d, y in zip(out, noisy.values(), strict=True)]
    write_views(ctx.work_dir / "denoised", dict(zip(noisy, out, strict=True)))
    save_checkpoint(ctx.work_dir / MODEL_FILE, model)
    return DenoiseSummary(views=list(noisy), train=history_ends(model.history), objective=objective,
                          dark_clipped_fraction=dark_clipped_fraction,
                          training_restarts=list(model.restarts),  # a diverged training, restarted
                          pd_stride=stride, noise_level_by_stride_255=levels.levels_by_stride_255() or None,
                          noise=noise_levels(noisy, stds)).to_json()  # the report's noise level


def _denoise_photos(photos: list[np.ndarray], n2v, s, seed: int):
    """(denoised photos, each photo's noise std, the trained model): the denoise stage's network and steps."""
    from denoise.parallel import one_thread_per_task
    from denoise.self_supervised import denoise_with_method, r2r_noise_std, train_with_method

    # One torch thread per task for training and inference alike (`denoise.parallel`): the UNet's outputs
    # differ in the last float bits between thread counts, enough to flip a PNG level now and then.
    with one_thread_per_task():
        # Each photo's noise std, estimated once: R2R's recorruption and both networks' clipping correction
        # use it, and the report records it (N2V's fusion estimates its own).
        stds = [r2r_noise_std(im) for im in photos]
        given = None if n2v.method == "n2v" else stds
        model = train_with_method(photos, n2v, seed=seed, device=s.device, noise_sigma=given)
        out = denoise_with_method(model, photos, n2v, passes=s.passes, seed=seed, noise_sigma=given,
                                  wiener=s.wiener, grouped=s.grouped)
    return out, stds, model


def align(ctx: StageContext) -> Mapping[str, object]:
    """Pose-free alignment of the denoised images (`mvgeo.align`), written as `mvgeo align` writes it
    (`ctx.settings`: `AlignStageSettings`), with the stage's decisions (`AlignDecisions`) in align.json and
    in the summary. In round 1 with `AlignSettings.photos` "noisy_first" or "better_of", the noisy photos
    (`ctx.inputs["noisy"]`, under the denoised photos' names) are aligned too (`_align_first_round`)."""
    from mvgeo.align import align_images

    s = ctx.settings
    cfg = s.align
    no_prior = ""
    files = list(view_files(ctx.inputs["images"]).values())
    mode = s.reuse_intrinsics or "never"
    if "intrinsics" in ctx.inputs:  # the user's calibration (AlignSettings.intrinsics), at the working size
        align_images = functools.partial(align_images, intrinsics=working_camera(ctx.inputs["intrinsics"], files[0]))
        mode = "never"  # nothing to re-estimate in later rounds
    elif "working" in ctx.inputs and cfg.exif_focal:  # the input photos' EXIF focal: the working PNGs lack it
        prior, no_prior = working_focal_prior(ctx.inputs["working"])
        if prior is not None:
            align_images = functools.partial(align_images, focal_prior=prior)
        else:
            _log.info("no focal prior from the input photos' EXIF: %s", no_prior)
    previous = ctx.inputs.get("previous_align")
    if previous is None:
        noisy = view_files(ctx.inputs["noisy"]) if s.reads_noisy else None
        res = _align_first_round(align_images, files, noisy, cfg, keep_better=s.photos == "better_of")
    else:
        res = _align_keeping_better_geometry(align_images, files, cfg, Path(previous), mode,
                                             s.reuse_geometry or "never")
    aligned = res.alignment
    if no_prior and aligned.stats.focal_prior is None and not aligned.stats.known_intrinsics:
        aligned.stats.focal_prior_unavailable = f"the input photos: {no_prior}"  # not the working PNGs'
    out = ctx.work_dir / "align"
    res.write(out)  # sparse/0/*.bin, points.ply, align.json
    np.savez(out / "points.npz", xyz=np.asarray(aligned.points_xyz, np.float64),
             rgb=np.asarray(aligned.points_rgb, np.uint8), conf=np.asarray(aligned.points_conf, np.float64))
    summary = {"registered": len(aligned.sparse_model.images), "points": int(len(aligned.points_xyz)),
               "stats": json.loads(json.dumps(res.align_json(), default=str))}
    if res.decisions.geometry is not None:
        summary["geometry"] = res.decisions.geometry.to_json()
    if res.decisions.photos is not None:
        summary["photos"] = res.decisions.photos.to_json()
    return summary


def working_camera(intrinsics: Path, image: Path) -> Camera:
    """The calibration `intrinsics` (of the input photos) scaled to the size of the working photo `image`."""
    from mvgeo.align.intrinsics import read_intrinsics

    h, w = read_image(image).shape[:2]
    return read_intrinsics(intrinsics).scaled(w, h)


def _align_first_round(align_images, files: list[Path], noisy: dict[str, Path] | None, cfg, *,
                       keep_better: bool = False) -> AlignStageResult:
    """Round 1's alignment, with which photos it used (`AlignDecisions.photos`).

    Without `noisy` (stem -> file): the denoised `files`. With it, the noisy photos under the denoised
    photos' names, with the dense cloud (the splat's start) made of the denoised `files` (`align_images`'
    `cloud_images`); then
    - `keep_better` False ("noisy_first"): the denoised `files` only where the noisy photos are refused;
    - `keep_better` True ("better_of"): the denoised `files` as well, and the alignment whose camera
      centres the bundle adjustment determines better (`better_determined`); either one where the other
      is refused.
    The denoised photos are matched with the detector for noisy photos once noisy photos were tried
    (`denoised_photos_config`). Both refused: the denoised photos' refusal is raised.
    """
    noisy_refused = None
    from_noisy = None
    if noisy is not None:
        try:
            # The poses from the noisy photos, the dense cloud (the splat's start) from the denoised ones.
            from_noisy = align_images([noisy[f.stem] for f in files], cfg, names=[f.name for f in files],
                                      cloud_images=files)
            if not keep_better:
                return AlignStageResult(from_noisy, AlignDecisions(photos=PhotosDecision("noisy")))
        except (AlignmentRefusedError, DisconnectedViewsError) as exc:
            reason = str(exc).splitlines()[0]
            _log.warning("the noisy photos were refused by the alignment (%s); aligning the denoised ones",
                         reason[:300])
            noisy_refused = reason[:1000]
        cfg = denoised_photos_config(cfg)
    try:
        res = align_images(files, cfg)
    except (AlignmentRefusedError, DisconnectedViewsError) as exc:
        if from_noisy is None:
            raise as_pipeline_refusal(exc) from exc
        reason = str(exc).splitlines()[0]
        _log.warning("the denoised photos were refused by the alignment (%s); keeping the noisy photos' poses",
                     reason[:300])
        photos = PhotosDecision("noisy", denoised_refused=reason[:1000])
        return AlignStageResult(from_noisy, AlignDecisions(photos=photos))
    if from_noisy is not None:
        views = [f.name for f in files]
        keep_denoised, comparison = better_determined(res.sparse_model, res.stats, from_noisy.sparse_model,
                                                      from_noisy.stats, views)
        _log.info("round 1 keeps %s", comparison.reason)
        photos = PhotosDecision("denoised" if keep_denoised else "noisy", comparison=comparison)
        return AlignStageResult(res if keep_denoised else from_noisy, AlignDecisions(photos=photos))
    return AlignStageResult(res, AlignDecisions(photos=PhotosDecision("denoised", noisy_refused=noisy_refused)))


def denoised_photos_config(cfg):
    """`cfg` (an `AlignConfig`) for photos that come out of a denoiser: SIFT as for noisy photos first,
    the COLMAP-like sensitive detection only where that leaves the match graph cut.

    `mvgeo.align` starts with the sensitive detection on photos whose estimated noise is below
    `ClassicalPairConfig.sensitive_below_noise` (3/255), which is right for camera photos and wrong for
    denoised ones: their residual noise reads as low as a clean photo's (DTU scan24 at sigma 50, R2R's
    photos 2.0-2.4/255; the clean photos 1.5-2.8/255), but their finest texture is partly the
    denoiser's, and the sensitive detector's features there contradict the pairs. Measured on those
    photos: refused (3 views' pairs contradicted) with it, 12/12 at 1.1 deg median rotation error (max
    3.9) without it.
    """
    return dataclasses.replace(cfg, pairwise=dataclasses.replace(cfg.pairwise, sensitive_below_noise=0.0))


def as_pipeline_refusal(exc: DegenerateGeometryError | DisconnectedViewsError):
    """An alignment refusal as the pipeline reports it, with a fix for `denoise-gs run`.

    `mvgeo align` suggests `--allow-partial`, `--intrinsics` or `--ba`, options the pipeline does not have: it
    registers every photo or stops. Its fix names the photos to leave out (by stem: the input photos'
    extensions may differ from the working PNGs') or what to add. Other errors come back unchanged.
    """
    if not isinstance(exc, DisconnectedViewsError | AlignmentRefusedError):
        return exc
    stems = sorted(Path(v).stem for v in exc.views)
    if isinstance(exc, DisconnectedViewsError):
        return DisconnectedViewsError(exc.message, views=exc.views, path=exc.path, fix=(
            f"leave the photos {stems} out of the input folder (no usable pair relates them to the others), or "
            "add photos that overlap them" if stems else exc.fix))
    if exc.kind in ("views_unsupported", "positions_undetermined") and stems:
        fix = (f"leave the photos {stems} out of the input folder, or add photos between them and their "
               "neighbours (`mvgeo align --allow-partial` on the photos registers the others and shows which)")
    elif exc.kind == "focal_undetermined":
        fix = "pass --allow-focal-prior to keep COLMAP's prior focal length, or add photos with more parallax"
    else:
        fix = "add photos between the existing ones (more overlap between neighbouring views)"
    return exc.with_fix(fix)


def _align_keeping_better_geometry(align_images, files: list[Path], cfg, previous: Path, intrinsics_mode: str,
                                   geometry_mode: str) -> AlignStageResult:
    """Rounds >= 2: this round's alignment (with `reuse_intrinsics`), or the previous round's restricted to
    this round's views when `choose_geometry` prefers it; the choice in `AlignDecisions.geometry`."""
    error: DegenerateGeometryError | DisconnectedViewsError | None = None
    try:
        if intrinsics_mode == "never":
            res = AlignStageResult(align_images(files, cfg))
        else:
            res = _align_with_previous_calibration(align_images, files, cfg, previous, intrinsics_mode)
    except (DegenerateGeometryError, DisconnectedViewsError) as exc:  # e.g. the K views alone do not pin
        res, error = None, exc  # the cameras, or their re-denoised photos no longer relate every view
    prev_model = read_sparse_model(previous / "sparse" / "0")
    prev_stats = AlignStats.read(previous / "align.json")
    views = [Path(f).name for f in files]
    choice = choose_geometry(geometry_mode, views, (prev_model, prev_stats),
                             None if res is None else (res.alignment.sparse_model, res.alignment.stats),
                             current_error=None if error is None else str(error)[:500])
    if not choice.used_previous:
        if error is not None:
            raise as_pipeline_refusal(error) from error
        return dataclasses.replace(res, decisions=dataclasses.replace(res.decisions, geometry=choice))
    return _previous_geometry(previous, prev_model, prev_stats, choice)


def _previous_geometry(previous: Path, model: SparseModel, stats: AlignStats,
                       choice: GeometryChoice) -> AlignStageResult:
    """The previous round's alignment as this round's: its cameras and poses of `choice.views`, its
    points, its align.json with the uncertainty figures restricted to those views (what the next round
    compares against), and its decisions (the previous round's photos and calibration records) with
    `choice` as the geometry one."""
    from mvgeo.align import AlignResult

    views = list(choice.views)
    images = [model.image(v) for v in views]
    sub = SparseModel({im.camera_id: model.cameras[im.camera_id] for im in images}, images,
                      model.points_xyz, model.points_rgb)
    ba = stats.bundle_adjustment
    if ba is not None and ba.centre_std_ratio is not None:
        ba = dataclasses.replace(ba, centre_std_ratio=restricted_ratios(model, stats, views))
    out_stats = dataclasses.replace(stats, n_images=len(views), n_registered=len(views), bundle_adjustment=ba)
    pts = np.load(previous / "points.npz")
    decisions = dataclasses.replace(AlignDecisions.read(previous / "align.json"), geometry=choice)
    return AlignStageResult(AlignResult(sub, np.asarray(pts["xyz"], np.float64), np.asarray(pts["rgb"], np.uint8),
                                        np.asarray(pts["conf"], np.float64), out_stats), decisions)


def _align_with_previous_calibration(align_images, files: list[Path], cfg, previous: Path,
                                     mode: str) -> AlignStageResult:
    """Rounds >= 2: align, keeping the better-determined of this round's and the previous round's
    focal (`eval.pipeline.calibration`); the choice and both estimates in `AlignDecisions.inherited`."""
    camera, previous_std = previous_calibration(previous)
    offered = InheritedCalibration(focal_px=0.5 * (camera.fx + camera.fy), focal_log_std=previous_std, mode=mode,
                                   used=True)
    if mode == "auto":
        try:
            res = align_images(files, cfg)
        except DegenerateGeometryError as exc:  # e.g. no pair of this round determines the focal length
            offered = dataclasses.replace(offered, estimate_refused=str(exc)[:500])
        else:
            current_std = focal_log_std(res.stats, inherited=None)  # estimated here: the bundle adjustment's
            if not prefer_previous("auto", previous_std, current_std):
                kept_own = dataclasses.replace(offered, used=False, estimate_focal_log_std=current_std)
                return AlignStageResult(res, AlignDecisions(inherited=kept_own))
            focals = res.stats.focal_px
            offered = dataclasses.replace(offered, estimate_discarded=FocalEstimate(
                focal_px=float(np.median(list(focals.values()))) if focals else None, focal_log_std=current_std))
    res = align_images(files, cfg, intrinsics=camera)
    return AlignStageResult(res, AlignDecisions(inherited=offered))


def _train_splat(images_dir: Path, align_dir: Path, s: SplatStageSettings | FuseStageSettings,
                 noisy_dir: Path | None = None):
    """(training result, alignment's sparse model, view stems): a splat on `images_dir`'s views,
    initialised from the alignment in `align_dir`; with `noisy_dir` (and `s.noisy_detail.weight > 0`)
    its targets take back the noisy photos' finest band (`denoise.detail.noisy_detail_target`)."""
    from splat.train import train_gaussians

    sparse = read_sparse_model(align_dir / "sparse" / "0")
    pts = np.load(align_dir / "points.npz")
    stems = [n.rsplit(".", 1)[0] for n in sparse.names]
    images = read_views(images_dir, stems)
    weights = None
    if noisy_dir is not None:
        images, weights = noisy_detail_targets(images, read_views(noisy_dir, stems), s.noisy_detail)
    cameras = [sparse.camera_of(n) for n in sparse.names]
    cam_from_world = np.stack([sparse.image(n).cam_from_world for n in sparse.names])
    res = train_gaussians(list(images.values()), cameras, cam_from_world, pts["xyz"], pts["rgb"], s.train,
                          device=s.device)
    return res, sparse, stems, weights


def noisy_detail_targets(images: Mapping[str, np.ndarray], noisy: Mapping[str, np.ndarray], detail: NoisyDetail
                         ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """(stem -> the splat's target, stem -> the weight it took): each view's `noisy_detail_target`, its weight
    scaled by the noisy photo's noise std as the denoiser estimates it (`r2r_noise_std`; a per-pixel map's
    median, as `report.md` states it)."""
    from denoise.self_supervised import r2r_noise_std

    targets, weights = {}, {}
    for k, img in images.items():
        sigma = r2r_noise_std(noisy[k])
        sigma = float(sigma.median()) if not isinstance(sigma, float | int) else float(sigma)
        weights[k] = noisy_detail_weight(detail, sigma)
        targets[k] = noisy_detail_target(img, noisy[k], detail, sigma)
    return targets, weights


def splat(ctx: StageContext) -> Mapping[str, object]:
    """Gaussian splatting with pose optimisation, initialised from the alignment (`ctx.settings`:
    `SplatStageSettings`). With `noisy_detail.weight > 0` the runner also passes the noisy working photos
    (`ctx.inputs["noisy"]`), whose finest band the targets take back (`PipelineConfig.splat.noisy_detail`).
    Returns a `SplatSummary`'s JSON."""
    from splat.ply import write_gaussian_ply

    s: SplatStageSettings = ctx.settings
    noisy = None
    if s.noisy_detail.weight > 0:
        if "noisy" not in ctx.inputs:
            raise ValueError("splat: noisy_detail is on but the runner passed no noisy photos (inputs['noisy'])")
        noisy = ctx.inputs["noisy"]
    res, sparse, stems, weights = _train_splat(ctx.inputs["images"], ctx.inputs["align"], s, noisy)
    write_gaussian_ply(ctx.work_dir / "point_cloud.ply", res.model)
    optimised = [PosedImage(im.name, im.camera_id, np.asarray(res.cam_from_world_optimized[i])[:3])
                 for i, im in enumerate(sparse.images)]
    write_sparse_model(ctx.work_dir / "sparse" / "0",
                       SparseModel(sparse.cameras, optimised, sparse.points_xyz, sparse.points_rgb), binary=True)
    history = dataclasses.asdict(res.history) if dataclasses.is_dataclass(res.history) else res.history
    detail = NoisyDetailRecord(s.noisy_detail, weights) if weights is not None else None
    return SplatSummary(views=stems, train=history_ends(history), noisy_detail=detail,
                        timings_s=dict(res.timings_s)).to_json()


#: Weight of the noisy photos' render in `fuse` (the denoised photo gets 1 - FUSE_WEIGHT): the plain mean
#: of two estimates of comparable quality (on `llff_like` 24.1 and 24.3 dB against the clean training
#: views), fixed a priori, not fitted to a scene.
FUSE_WEIGHT = 0.5


def fuse_images(denoised: np.ndarray, render: np.ndarray, weight: float = FUSE_WEIGHT) -> np.ndarray:
    """(1 - weight) * denoised + weight * render, both (H, W, 3) float in [0, 1]."""
    if denoised.shape != render.shape:
        raise ValueError(f"fuse: denoised {denoised.shape} and render {render.shape} differ in shape")
    return ((1.0 - weight) * denoised + weight * render).astype(np.float32)


#: Largest difference between rotation-matrix entries of two cam_from_world that `noisy_splat_reuse`
#: treats as the same pose. A handed-over pose goes through COLMAP's binary format once more, whose
#: quaternion round trip changes entries by up to ~1e-15 (translations, intrinsics and points are stored
#: as float64 and come back bit-exact); any re-estimated pose differs by many orders of magnitude more.
ROTATION_ATOL = 1e-12


@dataclass(frozen=True)
class NoisySplatReuse:
    """Whether a round's fuse stage takes the previous round's noisy-photo renders (`noisy_splat_reuse`).

    Attributes:
        reused: True: the previous round's renders of `views` are this round's.
        reason: the check that decided, in words.
    """

    reused: bool
    reason: str


def _same_camera(a, b) -> bool:
    return a.model == b.model and (a.width, a.height) == (b.width, b.height) and np.array_equal(a.params, b.params)


def _same_pose(cam_from_world_a: np.ndarray, cam_from_world_b: np.ndarray) -> bool:
    """(3, 4) cam_from_world each; equal translations, rotations within `ROTATION_ATOL`."""
    a, b = np.asarray(cam_from_world_a, np.float64), np.asarray(cam_from_world_b, np.float64)
    return bool(np.array_equal(a[:, 3], b[:, 3]) and np.abs(a[:, :3] - b[:, :3]).max() <= ROTATION_ATOL)


def noisy_splat_reuse(views: Sequence[str], *, align_dir: Path, previous_align_dir: Path, noisy_dir: Path,
                      previous_noisy_dir: Path, previous_renders_dir: Path) -> NoisySplatReuse:
    """Whether the previous round's noisy-photo splat was trained from what this round's would be.

    The previous round's fuse stage trained its splat on the noisy photos in `previous_noisy_dir` from
    the alignment in `previous_align_dir` and rendered every view into `previous_renders_dir`. This
    round's would train on `views` of `noisy_dir` from `align_dir`. Reuse needs: a previous render of
    every view; the same noisy image files (sha256); every view's camera and cam_from_world in this
    round's alignment equal to the previous round's (`_same_camera`, `_same_pose`); the same initial
    points (points.npz `xyz` and `rgb`). The previous splat then started from the same cameras and
    points and saw these views plus the previous round's others; its training settings are the
    run's (`PipelineConfig.splat`), the same in every round but for the seed.

    Args:
        views: this round's view stems.
        align_dir, previous_align_dir: align stage folders (`sparse/0/`, `points.npz`).
        noisy_dir, previous_noisy_dir: the noisy photos each round's fuse stage reads.
        previous_renders_dir: the previous round's `noisy_renders/`.
    """
    renders = view_files(previous_renders_dir)
    missing = [v for v in views if v not in renders]
    if missing:
        return NoisySplatReuse(False, f"the previous round has no noisy-photo render of {missing}")
    noisy, previous_noisy = view_files(noisy_dir), view_files(previous_noisy_dir)
    for v in views:
        if v not in noisy or v not in previous_noisy or file_sha256(noisy[v]) != file_sha256(previous_noisy[v]):
            return NoisySplatReuse(False, f"the noisy photo {v} differs from the previous round's")
    model = read_sparse_model(align_dir / "sparse" / "0")
    previous = read_sparse_model(previous_align_dir / "sparse" / "0")
    by_stem = {n.rsplit(".", 1)[0]: n for n in model.names}
    previous_by_stem = {n.rsplit(".", 1)[0]: n for n in previous.names}
    for v in views:
        if v not in by_stem or v not in previous_by_stem:
            return NoisySplatReuse(False, f"view {v} is not registered in both alignments")
        n, pn = by_stem[v], previous_by_stem[v]
        if not _same_camera(model.camera_of(n), previous.camera_of(pn)):
            return NoisySplatReuse(False, f"the intrinsics of {v} differ from the previous round's")
        if not _same_pose(model.image(n).cam_from_world, previous.image(pn).cam_from_world):
            return NoisySplatReuse(False, f"the cam_from_world of {v} differs from the previous round's")
    pts, previous_pts = np.load(align_dir / "points.npz"), np.load(previous_align_dir / "points.npz")
    if not all(np.array_equal(pts[k], previous_pts[k]) for k in ("xyz", "rgb")):
        return NoisySplatReuse(False, "the alignment's points differ from the previous round's")
    return NoisySplatReuse(True, "the same noisy photos, cameras, poses and points as the previous round's splat")


def _recorded_geometry_choice(align_dir: Path) -> RecordedGeometryChoice | None:
    """The align stage's rounds >= 2 decision in `align_dir`'s align.json (`AlignDecisions.geometry`) as
    the fuse stage's summary records it (used_previous, reason); None without one."""
    stats_file = align_dir / "align.json"
    if not stats_file.is_file():
        return None
    choice = AlignDecisions.read(stats_file).geometry
    if choice is None:
        return None
    return RecordedGeometryChoice(choice.used_previous, choice.reason)


def fuse(ctx: StageContext) -> Mapping[str, object]:
    """Extension (`PipelineConfig.fuse_noisy_splat`): the round's denoised photos averaged with renders,
    at their own (optimised) poses, of a splat trained on the *noisy* photos with the round's alignment.

    The splat of 12 noisy views keeps the scene's fine texture (the same in every view) and averages
    the noise (different in every view); the denoiser removes noise and texture alike. Their errors
    differ, so the mean is better than either (CHANGELOG.md, 2026-11-22). `ctx.settings`: a
    `FuseStageSettings`.

    Rounds >= 2 with `reuse_noisy_splat` (the runner then passes `previous_align`, `previous_noisy` and
    `previous_noisy_renders`): when `noisy_splat_reuse` finds the previous round's splat trained from
    the same noisy photos, cameras, poses and points, its renders of this round's views are copied
    (same bytes) instead of training a new splat on a subset of the same photos. The summary (a
    `FuseSummary`'s JSON) says which (`noisy_splat`: "reused" or "trained") and why (`noisy_splat_reason`).
    """
    s = ctx.settings
    # The alignment's registered views, in its order (those the splat trains on).
    stems = [n.rsplit(".", 1)[0] for n in read_sparse_model(ctx.inputs["align"] / "sparse" / "0").names]
    previous = ctx.inputs.get("previous_noisy_renders")
    if not s.reuse_noisy_splat:
        decision = NoisySplatReuse(False, "reuse_noisy_splat is off" if s.reuse_noisy_splat is False
                                   else "round 1 has no previous round")
    elif previous is None:
        decision = NoisySplatReuse(False, "no previous round's noisy-photo renders were given")
    else:
        decision = noisy_splat_reuse(stems, align_dir=ctx.inputs["align"],
                                     previous_align_dir=ctx.inputs["previous_align"],
                                     noisy_dir=ctx.inputs["noisy"], previous_noisy_dir=ctx.inputs["previous_noisy"],
                                     previous_renders_dir=previous)
    out_renders = ctx.work_dir / "noisy_renders"
    if decision.reused:
        out_renders.mkdir(parents=True)
        files = view_files(previous)
        for v in stems:
            shutil.copyfile(files[v], out_renders / files[v].name)
        renders = read_views(out_renders, stems)
        timings: dict[str, float] = {}
    else:
        from splat.render import render_views

        res, sparse, stems, _ = _train_splat(ctx.inputs["noisy"], ctx.inputs["align"], s)
        cameras = [sparse.camera_of(n) for n in sparse.names]
        cam_from_world = np.stack([np.asarray(m)[:3] for m in res.cam_from_world_optimized])
        renders = dict(zip(stems, render_views(res.model, cameras, cam_from_world), strict=True))
        write_views(out_renders, renders)
        timings = dict(res.timings_s)
    denoised = read_views(ctx.inputs["images"], stems)
    write_views(ctx.work_dir / "fused", {k: fuse_images(denoised[k], renders[k]) for k in stems})
    return FuseSummary(views=stems, weight=FUSE_WEIGHT, noisy_splat="reused" if decision.reused else "trained",
                       noisy_splat_reason=decision.reason,
                       align_geometry=_recorded_geometry_choice(ctx.inputs["align"]),
                       timings_s=timings or None).to_json()


def render(ctx: StageContext) -> Mapping[str, object]:
    """Render the trained Gaussians at every pose of the round's `sparse/0` (`ctx.settings`:
    `RenderStageSettings`)."""
    from splat.ply import read_gaussian_ply
    from splat.render import render_views

    sparse = read_sparse_model(ctx.inputs["sparse"] / "0")
    model = read_gaussian_ply(ctx.inputs["scene"], device=ctx.settings.device)
    cameras = [sparse.camera_of(n) for n in sparse.names]
    cam_from_world = np.stack([sparse.image(n).cam_from_world for n in sparse.names])
    images = render_views(model, cameras, cam_from_world)
    stems = [n.rsplit(".", 1)[0] for n in sparse.names]
    write_views(ctx.work_dir / "renders", dict(zip(stems, images, strict=True)))
    return {"views": stems}


def select(ctx: StageContext) -> Mapping[str, object]:
    """Views for the next round: pose k-means (K = views) + sharpest (Laplacian variance) per cluster
    (`ctx.settings`: `SelectStageSettings`), in selection.json; returns a `SelectSummary`'s JSON."""
    s = ctx.settings
    sparse = read_sparse_model(ctx.inputs["sparse"] / "0")
    stems = [n.rsplit(".", 1)[0] for n in sparse.names]
    if not s.select_views or len(stems) <= s.views:
        selection = {"names": stems, "method": "all" if not s.select_views else "all (N <= K)"}
    else:
        from denoise.view_selection import select_views

        images = read_views(ctx.inputs["images"], stems)
        cfw = {stem: sparse.image(n).cam_from_world for stem, n in zip(stems, sparse.names, strict=True)}
        sel = select_views(cfw, images, s.views, seed=ctx.seed)
        selection = {"names": list(sel.names), "method": "kmeans+laplacian",
                     "cluster_of": {k: int(v) for k, v in dict(sel.cluster_of).items()},
                     "laplacian_var": {k: float(v) for k, v in dict(sel.laplacian_var).items()}}
    (ctx.work_dir / "selection.json").write_text(json.dumps(selection, indent=2) + "\n")
    return SelectSummary(selected=list(selection["names"]), method=selection["method"]).to_json()


def refine(ctx: StageContext) -> Mapping[str, object]:
    """Rounds >= 2: fine-tune the UNet against the previous renders on the selected views, denoise them
    (`ctx.settings`: `RefineStageSettings`). Where the photos' noise is correlated between neighbouring
    pixels, as in round 1 (`denoise`), the photos and the renders are pixel-shuffled alike and the network
    fine-tuned and applied on the sub-images it learned on. Returns a `RefineSummary`'s JSON."""
    from denoise.inference import denoise_images
    from denoise.model import load_checkpoint, save_checkpoint
    from denoise.parallel import one_thread_per_task
    from denoise.pixel_shuffle import shuffled, stride_for, unshuffled
    from denoise.round2 import refine_round2

    s = ctx.settings
    names = json.loads((ctx.inputs["selection"]).read_text())["names"]
    noisy = read_views(ctx.inputs["noisy"], names)
    renders = read_views(ctx.inputs["renders"], names)
    model = load_checkpoint(ctx.inputs["model"], device=s.device)
    stride = stride_for(list(noisy.values()), s.pd_stride).stride
    photos, targets = list(noisy.values()), list(renders.values())
    if stride > 1:
        photos, targets = shuffled(photos, stride), shuffled(targets, stride)
    # Trust target (the render only where it agrees with the photo within the noise) and the
    # blind-spot-loss guard: see denoise.round2.refine_round2.
    # Fine-tuning and inference with one torch thread per task, as in `denoise`: the result would depend on it.
    with one_thread_per_task():
        model, r2 = refine_round2(model, photos, targets, s.round2, seed=ctx.seed)
        # Keep the observation blend (denoise.fusion) for the fine-tuned model too: most of round 1's
        # quality comes from it, and without it round 2 fell from 23.97 to 20.92 dB on the demo scene
        # (8 views, 192x144, sigma 25/255).
        if r2.reverted and "previous" in ctx.inputs:
            # The guard kept the previous network: keep the previous round's images too (identical
            # up to the random maskings of inference), so a reverted round changes nothing.
            out = list(read_views(ctx.inputs["previous"], names).values())
        else:
            out = denoise_images(model, photos, passes=s.passes, seed=ctx.seed, fuse=True)
            if stride > 1:
                out = unshuffled(out, stride, [im.shape for im in noisy.values()])
    write_views(ctx.work_dir / "denoised", dict(zip(names, out, strict=True)))
    save_checkpoint(ctx.work_dir / MODEL_FILE, model)
    return RefineSummary(views=list(names), train=history_ends(model.history), pd_stride=stride,
                         round2=r2.to_json()).to_json()


#: The code each product stage runs besides `eval/pipeline/stages.py`: all of `eval.pipeline` (views'
#: PNG writing, calibration, stage settings) and the component packages it calls, each with the project
#: packages those import (`splat` imports `denoise.losses`; `denoise` and `splat` import `mvgeo`).
#: Their source digests enter the stage keys (`eval.pipeline.stage`'s rule), so a changed constant or
#: function in any of them re-runs the stage and the stages after it.
STAGE_CODE: dict[str, tuple[str, ...]] = {
    "denoise": ("eval.pipeline", "denoise", "mvgeo"),
    "align": ("eval.pipeline", "mvgeo"),
    "fuse": ("eval.pipeline", "splat", "denoise", "mvgeo"),
    "splat": ("eval.pipeline", "splat", "denoise", "mvgeo"),
    "render": ("eval.pipeline", "splat", "denoise", "mvgeo"),
    "select": ("eval.pipeline", "denoise", "mvgeo"),
    "refine": ("eval.pipeline", "denoise", "mvgeo"),
}


def product_stages() -> PipelineStages:
    """The real Denoise-GS stages."""
    from eval.pipeline.publish import EXPORT_CODE, export

    return PipelineStages(denoise=denoise, align=align, splat=splat, render=render, select=select, refine=refine,
                          fuse=fuse, export=export, code={**STAGE_CODE, "export": EXPORT_CODE})
