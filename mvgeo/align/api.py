"""`align_images`: image files (or arrays) in, poses + intrinsics + dense cloud out.

The stages, each in its module: inputs (`inputs`) -> features and matches, once per image and pair, and the
pair geometry as a `PairSet` (`classical_pairs`, or any `PointmapModel`) -> candidate solutions, each a start
(`init`: DUSt3R chaining or rotation averaging), the DUSt3R global alignment (`global_align`), the bundle
adjustment on every verified pair (`bundle`) and a verdict with typed reasons (`verdict`); one policy
generates the candidates and one rule chooses (`policy`) -> the dense cloud (`cloud`) -> the report
(`stats.AlignStats`) and the writer (`writer`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mvgeo.align.classical_pairs import ClassicalPointmapModel
from mvgeo.align.cloud import DenseCloud, dense_cloud
from mvgeo.align.config import DEFAULT, PREVIEW, AlignConfig
from mvgeo.align.global_align import GlobalAlignResult
from mvgeo.align.graph import make_pairs
from mvgeo.align.inputs import AlignInputs, load_inputs
from mvgeo.align.intrinsics import FocalPrior, choose_focal_prior
from mvgeo.align.locate import Located
from mvgeo.align.pairs import PairSet, PointmapModel
from mvgeo.align.policy import choose_solution
from mvgeo.align.principal import with_principal_point
from mvgeo.align.result import AlignResult
from mvgeo.align.solve import Candidate, cloud_alignment
from mvgeo.align.stats import AlignStats, BundleStats, CandidateSummary, FocalPriorStats, InconsistentPair, LocatedView
from mvgeo.align.verdict import centre_std_ratio
from mvgeo.align.writer import write_align_result
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.threads import native_threads
from mvgeo.common.timing import StageTimer
from mvgeo.sparse_model import PosedImage, SparseModel

__all__ = ["AlignConfig", "AlignResult", "FocalPrior", "PREVIEW", "align_images", "write_align_result"]


def align_images(images: Sequence[Path] | Sequence[np.ndarray], config: AlignConfig = DEFAULT, *,
                 names: Sequence[str] | None = None, intrinsics: Camera | None = None,
                 model: PointmapModel | None = None, focal_prior: FocalPrior | None = None,
                 cloud_images: Sequence[Path] | Sequence[np.ndarray] | None = None) -> AlignResult:
    """Pose-free reconstruction of a few views: pairwise pointmaps, DUSt3R global alignment, bundle adjustment.

    Args:
        images: image files, or (H, W, 3) float32 RGB arrays in [0, 1], all the same size.
        config: `AlignConfig`.
        names: image names for the output (default: file names, or 000.png, ...).
        intrinsics: known camera (at the input size, any supported model): images are undistorted and the
            focal is fixed instead of estimated.
        model: a `PointmapModel` (default: `ClassicalPointmapModel`).
        focal_prior: the focal length the default model's pairs start at (e.g. the EXIF focal of the photos
            these images were made from; ignored when `intrinsics` is given); default: the image files' common
            EXIF focal (`AlignConfig.exif_focal`), if any. The bundle adjustment refines it; kept within
            `AlignConfig.refocus_min_change`, it counts as determining the focal.
        cloud_images: the same views in the same order and size, whose pixels the dense cloud is made of (the
            dense stereo's flows and the points' colours) instead of `images`'; the poses come from `images`
            alone. E.g. photos that went through a denoiser, where `images` are the noisy photos: their
            features relate the views without the denoiser's texture, and the stereo and colours are
            cleaner in the denoised ones.

    Raises:
        InputError: too few/corrupt/duplicate/mixed-size images; `DisconnectedViewsError` (an `InputError`): a
            disconnected pair graph (names the images that could not be connected).
        DegenerateGeometryError: no candidate solution is supported by the evidence (the reason names the
            views), or the alignment failed numerically.
    """
    with native_threads(config.native_threads):
        timer = StageTimer()
        with timer.stage("load"):
            inputs = load_inputs(images, names=names, intrinsics=intrinsics, max_size_px=config.max_size_px)
        pixels = None if cloud_images is None else _cloud_pixels(inputs, cloud_images, intrinsics, config)
        prior, no_prior = choose_focal_prior(images, known_intrinsics=inputs.intrinsics is not None,
                                             given=focal_prior, read_exif=config.exif_focal)
        if model is None:
            model = ClassicalPointmapModel(config.pairwise, K_align=inputs.K_align, seed=config.seed,
                                           focal_prior_px=None if prior is None else prior.focal_px(inputs.align_wh))
        elif focal_prior is not None:
            raise InputError("a focal prior was given with a custom pair model, which would not use it",
                             fix="pass the prior to the model itself, or leave focal_prior out")
        elif prior is not None:
            prior, no_prior = None, "a custom pair model finds its own focal"
        pair_list = make_pairs(len(inputs), config.pairs)
        with timer.stage("pairwise"):
            pairs = model.predict_pairs(inputs.small, pair_list)
        chosen, candidates, contradicted = choose_solution(inputs, pairs, pair_list, model, config, timer)
        chosen, principal = with_principal_point(chosen, config, timer)
        aligned = functools.cache(lambda: cloud_alignment(chosen, timer))  # run only if the cloud asks for it
        cloud_inputs = chosen.inputs if pixels is None else dataclasses.replace(pixels.restricted(
            [inputs.names.index(n) for n in chosen.inputs.names]), K_align=chosen.inputs.K_align)
        cloud = dense_cloud(cloud_inputs, chosen.result, chosen.ba, [(p.i, p.j) for p in chosen.pairs.predictions],
                            chosen.pairs.matches, config, timer, chosen.graph.grid_to_align, aligned=aligned)
        sparse = _sparse_model(chosen, cloud)
        ran_full = chosen.start_values is None or aligned.cache_info().currsize > 0
        alignment = (aligned() if ran_full else chosen.result,
                     chosen.align_config.iters if ran_full else config.candidate_align_iters)
        stats = _stats(chosen, candidates, pairs, len(pair_list), len(inputs), sparse, cloud, config, timer,
                       alignment)
        stats = dataclasses.replace(stats, chain_start_contradicted=None if contradicted is None else
                                    round(contradicted, 4),
                                    principal_point=principal,
                                    focal_prior_unavailable=no_prior, focal_prior=None if prior is None else
                                    FocalPriorStats(prior.source, round(prior.focal_35mm, 3),
                                                    round(prior.focal_px(inputs.input_wh), 2)))
        return AlignResult(sparse, cloud.xyz, cloud.rgb, cloud.conf, stats)


def _cloud_pixels(inputs: AlignInputs, cloud_images, intrinsics: Camera | None, config: AlignConfig) -> AlignInputs:
    """`cloud_images` loaded as `inputs` were (the same names, undistortion and size), checked to match them."""
    if len(cloud_images) != len(inputs):
        raise InputError(f"{len(cloud_images)} cloud images for {len(inputs)} images",
                         fix="pass one cloud image per image, in the same order")
    def same_size(pixels: AlignInputs) -> AlignInputs:
        if pixels.input_wh != inputs.input_wh:
            raise InputError(f"the cloud images are {pixels.input_wh[0]}x{pixels.input_wh[1]}, the images "
                             f"{inputs.input_wh[0]}x{inputs.input_wh[1]}", fix="pass the same views at the same size")
        return pixels

    def about_the_cloud_images(exc: InputError) -> InputError:  # a problem of the set names no file: say whose
        return exc if exc.path is not None else InputError(f"the cloud images: {exc.message}", fix=exc.fix)

    try:
        return same_size(load_inputs(cloud_images, names=inputs.names, intrinsics=intrinsics,
                                     max_size_px=config.max_size_px))
    except InputError as exc:
        if intrinsics is None:
            raise about_the_cloud_images(exc) from exc
        # The calibration fits the images (checked on them): a size mismatch is the cloud images', say so.
        try:
            same_size(load_inputs(cloud_images, names=inputs.names, intrinsics=None,
                                  max_size_px=config.max_size_px))
        except InputError as plain:
            raise about_the_cloud_images(plain) from plain
        raise about_the_cloud_images(exc) from exc


def _sparse_model(c: Candidate, cloud: DenseCloud) -> SparseModel:
    """PINHOLE cameras at the input size: one camera when the views share their intrinsics (known, or one
    shared focal), as COLMAP's single-camera mode writes them; else one per view.

    An estimated focal is one of square pixels at the alignment size (the bundle adjustment's, the dense
    stereo's; `grid_to_align` converts the pointmap grid's by its width), scaled to the input size per axis
    as the images were resized: where the grid's aspect ratio rounds differently from the image's (e.g. 250x165
    with a 96x63 grid), scaling fy by the grid's height would make it 0.6 % longer than fx."""
    (W0, H0), K = c.inputs.input_wh, c.inputs.intrinsics
    (Wa, Ha) = c.inputs.align_wh
    f = c.result.focal_px * c.graph.grid_to_align  # alignment pixels
    one_camera = K is not None or bool(np.all(f == f[0]))
    # Without intrinsics, the principal point is the image centre unless the views determined it (an estimated
    # K_align, `mvgeo.align.principal`).
    centre = ((W0 / 2.0, H0 / 2.0) if c.inputs.K_align is None
              else (c.inputs.K_align[0, 0, 2] * W0 / Wa, c.inputs.K_align[0, 1, 2] * H0 / Ha))
    cameras, posed = {}, []
    for v, name in enumerate(c.inputs.names):
        cam = (Camera.pinhole(K.fx, K.fy, K.cx, K.cy, W0, H0) if K is not None else
               Camera.pinhole(f[v] * W0 / Wa, f[v] * H0 / Ha, *centre, W0, H0))
        cam_id = 1 if one_camera else v + 1
        cameras.setdefault(cam_id, cam)
        posed.append(PosedImage(name, cam_id, c.result.cam_from_world[v]))
    return SparseModel(cameras, posed, cloud.xyz, cloud.rgb)


def _located_view(names: Sequence[str], x: Located, outcome: str) -> LocatedView:
    deg = None if np.isnan(x.rotation_deg) else round(x.rotation_deg, 3)
    return LocatedView(names[x.view], x.n_inliers, deg, x.n_points, outcome)


def _bundle_stats(c: Candidate) -> BundleStats | None:
    if c.ba is None:
        return None
    b, r = c.ba, c.depth_rescale
    return BundleStats(b.n_points, b.n_observations, b.reproj_rms_before_px, b.reproj_rms_after_px,
                       b.reproj_median_before_px, b.reproj_median_after_px, b.focal_log_std, b.solver,
                       centre_std_ratio(b),
                       None if r is None else [round(float(k), 4) for k in r[0]],
                       None if r is None else [None if np.isnan(m) else round(float(m), 4) for m in r[1]],
                       b.readjusted, list(c.inputs.names))


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x if isinstance(x, (bool, int, float, str)) or x is None else str(x)


def _stats(c: Candidate, candidates: list[CandidateSummary], pairs: PairSet, n_pairs: int, n_images: int,
           sparse: SparseModel, cloud: DenseCloud, config: AlignConfig, timer: StageTimer,
           alignment: tuple[GlobalAlignResult, int]) -> AlignStats:
    """`alignment`: the global alignment that was run last for the chosen candidate, and its iterations."""
    names = c.inputs.names
    ga, ga_iters = alignment
    Hp, Wp = c.result.depth[0].shape
    return AlignStats(
        n_images=n_images, n_registered=len(names), input_size_wh=list(c.inputs.input_wh),
        align_size_wh=list(c.inputs.align_wh), pointmap_size_wh=[Wp, Hp], n_pairs=n_pairs,
        n_pairs_ok=len(c.pairs.predictions), n_pairs_verified=len(pairs.geometries),
        failed_pairs=c.graph.failed, pairs_rejected_by_loops=c.graph.rejected, unregistered=c.unregistered,
        iterations=ga_iters, init_loss=ga.init_loss, final_loss=ga.final_loss,
        focal_px={im.name: sparse.cameras[im.camera_id].fx for im in sparse.images},
        known_intrinsics=c.inputs.intrinsics is not None, shared_focal=c.align_config.shared_focal,
        bundle_adjustment=_bundle_stats(c), dense_stereo=cloud.stereo,
        focal_determined_by_pairs=c.pairs.focal_determined, sensitive_features=c.pairs.sensitive_features,
        initial_poses=c.start, candidates=candidates,
        pairs_dropped_as_inconsistent=[list(d) for d in c.dropped],
        pair_consistency_min=min((k.explained_fraction for k in c.checks), default=float("nan")),
        pairs_inconsistent=[InconsistentPair(names[k.i], names[k.j], round(k.explained_fraction, 3),
                                             None if np.isnan(k.rotation_deviation_deg)
                                             else round(k.rotation_deviation_deg, 2)) for k in c.bad],
        views_located_by_points=[_located_view(names, x, outcome) for x, outcome in
                                 [(x, "re-posed") for x in c.relocated]
                                 + [(x, "kept" if x.ok else "placed elsewhere" if x.placed_elsewhere
                                     else "not located") for x in c.located]],
        n_points=int(len(cloud.xyz)), mean_confidence=float(cloud.conf.mean()) if len(cloud.conf) else float("nan"),
        timings_s=timer.as_dict(), config=_jsonable(dataclasses.asdict(config)))
