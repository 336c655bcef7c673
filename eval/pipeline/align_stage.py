"""The product's align stage (`align`): pose-free alignment of a round's photos with `mvgeo.align`, and the
helpers it decides with: which photos round 1 aligns, and in rounds >= 2 whether the previous round's
calibration or geometry is kept (`eval.pipeline.calibration`, `eval.pipeline.align_decisions`)."""

from __future__ import annotations

import dataclasses
import filecmp
import functools
import json
import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

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
from eval.pipeline.inputs import working_focal_prior
from eval.pipeline.stage import StageContext
from eval.pipeline.summaries import AlignSummary
from eval.pipeline.views import view_files
from mvgeo.align.stats import AlignStats, BundleStats
from mvgeo.camera import Camera
from mvgeo.common.errors import AlignmentRefusedError, DegenerateGeometryError, DisconnectedViewsError, InputError
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import SparseModel, read_sparse_model

__all__ = ["align", "as_pipeline_refusal", "denoised_photos_config", "working_camera"]

_log = logging.getLogger(__name__)


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
        res = _align_first_round(align_images, files, noisy, cfg, keep_better=s.photos == "better_of",
                                 identical=noisy is not None and same_photos(files, noisy))
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
    return AlignSummary(registered=len(aligned.sparse_model.images), points=int(len(aligned.points_xyz)),
                        stats=json.loads(json.dumps(res.align_json(), default=str)),
                        geometry=res.decisions.geometry, photos=res.decisions.photos).to_json()


def working_camera(intrinsics: Path, image: Path) -> Camera:
    """The calibration `intrinsics` (of the input photos) scaled to the size of the working photo `image`."""
    from mvgeo.align.intrinsics import read_intrinsics

    h, w = read_image(image).shape[:2]
    return read_intrinsics(intrinsics).scaled(w, h)


def same_photos(files: list[Path], noisy: Mapping[str, Path]) -> bool:
    """Whether every denoised photo in `files` holds the same pixels as its noisy photo (`noisy`: stem ->
    file), as where the denoise stage passed clean photos through (`pass_clean_below_255`). Stops at the
    first photo that differs, so noisy photos cost one read of each of two files. A file that does not
    decode is not the same photo (the alignment, reading it, refuses it by name)."""
    for f in files:
        other = noisy.get(f.stem)
        if other is None:
            return False
        if filecmp.cmp(f, other, shallow=False):
            continue
        try:
            if not np.array_equal(read_image(f), read_image(other)):
                return False
        except InputError:  # not an image: the alignment reads it and says so
            return False
    return True


def _align_first_round(align_images, files: list[Path], noisy: dict[str, Path] | None, cfg, *,
                       keep_better: bool = False, identical: bool = False) -> AlignStageResult:
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

    `identical` (`same_photos`: the denoised photos are the noisy ones, passed through undenoised): an
    alignment of the noisy photos is kept as it is, under either mode, since the denoised photos' would align
    the same pixels again; where the noisy photos are refused, the same pixels are still tried with the
    detector for denoised photos. The record says so (`PhotosDecision.identical`).
    """
    noisy_refused = None
    from_noisy = None
    if noisy is not None:
        try:
            # The poses from the noisy photos, the dense cloud (the splat's start) from the denoised ones.
            from_noisy = align_images([noisy[f.stem] for f in files], cfg, names=[f.name for f in files],
                                      cloud_images=files)
            if not keep_better or identical:
                return AlignStageResult(from_noisy, AlignDecisions(photos=PhotosDecision("noisy",
                                                                                         identical=identical)))
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
    return AlignStageResult(res, AlignDecisions(photos=PhotosDecision("denoised", noisy_refused=noisy_refused,
                                                                      identical=identical)))


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
    ba = None if stats.bundle_adjustment is None else _restricted_bundle_stats(model, stats, views)
    out_stats = dataclasses.replace(stats, n_images=len(views), n_registered=len(views), bundle_adjustment=ba)
    pts = np.load(previous / "points.npz")
    decisions = dataclasses.replace(AlignDecisions.read(previous / "align.json"), geometry=choice)
    return AlignStageResult(AlignResult(sub, np.asarray(pts["xyz"], np.float64), np.asarray(pts["rgb"], np.uint8),
                                        np.asarray(pts["conf"], np.float64), out_stats), decisions)


def _restricted_bundle_stats(model: SparseModel, stats: AlignStats, views: list[str]) -> BundleStats:
    """`stats.bundle_adjustment` with its per-view lists restricted to `views`, in that order, and `views` as
    the list they follow: `centre_std_ratio` re-expressed over the `views` cameras' spacing
    (`restricted_ratios`); a list that does not match the alignment's views becomes None."""
    ba = stats.bundle_adjustment
    before = list(model.names) if ba.views is None else list(ba.views)

    def pick(values: list | None) -> list | None:
        if values is None or len(values) != len(before) or not set(views) <= set(before):
            return None
        at = dict(zip(before, values, strict=True))
        return [at[v] for v in views]

    ratios = None if ba.centre_std_ratio is None else restricted_ratios(model, stats, views)
    return dataclasses.replace(ba, centre_std_ratio=ratios, dense_depth_scale=pick(ba.dense_depth_scale),
                               dense_depth_log_mad=pick(ba.dense_depth_log_mad), views=list(views))


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
