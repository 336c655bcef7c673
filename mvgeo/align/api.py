"""`align_images`: image files (or arrays) in, poses + intrinsics + dense cloud out; and its writer."""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from mvgeo.align.bundle import BundleConfig, BundleResult, bundle_adjust
from mvgeo.align.checks import PairCheck, pair_consistency, pair_rotation_deviation, views_without_consistent_pair
from mvgeo.align.classical_pairs import ClassicalPairConfig, ClassicalPointmapModel, pointmap_shape
from mvgeo.align.dense_stereo import DenseStereoConfig, stereo_depths
from mvgeo.align.global_align import GlobalAlignConfig, GlobalAlignResult, focal_estimates, global_align, pixel_rays
from mvgeo.align.graph import PairGraphSpec, components, make_pairs
from mvgeo.align.hole_fill import HoleFillConfig, fill_depth_holes
from mvgeo.align.intrinsics import undistort_image
from mvgeo.align.loops import DEFAULT_MAX_LOOP_DEG, pair_rotations, reject_by_loops
from mvgeo.align.pairs import PairFailure, PairPrediction, PointmapModel
from mvgeo.align.rotation_averaging import init_from_averaged_rotations
from mvgeo.align.scene import covisibility_keep, pixel_downsample_by_confidence, voxel_downsample_by_confidence
from mvgeo.camera import Camera
from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.deps import cv2
from mvgeo.common.errors import ConfigError, DegenerateGeometryError, InputError
from mvgeo.common.imageio import read_image
from mvgeo.common.output import OutputPlan, as_output_plan
from mvgeo.common.threads import native_threads
from mvgeo.common.timing import StageTimer
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AlignConfig:
    """Options of `align_images` (defaults: the `mvgeo align` CLI's). Measured effects of the options:
    docs/bench/align.md (synthetic scenes, sweeps) and docs/bench/real.md (real photos).

    Attributes:
        max_size_px: long side of the images used for matching (640; larger images are downscaled once,
            and cameras are written at the input size).
        pairs: pair graph (`PairGraphSpec`).
        pairwise: options of the classical pair estimator (incl. the pointmap resolution
            `pointmap_size_px`).
        align: options of the global alignment (`shared_focal` lives there); default 100 iterations on
            every 4th pixel row/column, since the final poses come from the bundle adjustment.
        min_conf: output points need a confidence above this (2.0; 1 means no information).
        consistency_px: a pair's match is explained by the result when its Sampson distance under the
            final poses and focals is below this (2.0 px at `max_size_px`; without the bundle
            adjustment, pixels of the pointmap grid).
        min_pair_explained: pairs with a smaller explained fraction (0.5) are inconsistent; they are
            dropped and the problem solved once more.
        max_unexplained_fraction: if the inconsistent pairs still hold more than this fraction (0.1) of
            all verified matches, `align_images` raises `DegenerateGeometryError` instead of returning a
            wrong result.
        max_pair_rotation_deg: a pair whose relative rotation in the result is more than this off the
            one its inlier matches imply is inconsistent too (0: off). Catches wrong rotations of pairs
            whose epipolar geometry is nearly ambiguous (narrow field of view, few matches).
        max_focal_log_std: without known intrinsics and without any pair that determines the focal, the
            bundle adjustment must: a log-focal standard deviation above this (0.05) fails the alignment.
        max_centre_std_ratio: a view whose camera centre the bundle adjustment leaves uncertain (largest
            standard deviation with the other cameras held, `mvgeo.align.bundle_lm.camera_centre_std`) by
            more than this fraction (1.0) of the median distance between neighbouring cameras fails the
            alignment, or with `allow_partial` is left out: the feature tracks do not determine its
            position. 0: off. Reported in align.json `bundle_adjustment.centre_std_ratio`.
        reject_unsupported_views: a view all of whose verified pairs are inconsistent with the result
            (`mvgeo.align.checks.views_without_consistent_pair`) fails the alignment, or with
            `allow_partial` is left out, whatever share of the matches its pairs hold (True).
        points_budget: maximum number of output points (200 000; confidence-aware thinning).
        downsample: how the cloud is thinned to `points_budget`: "pixel" (default), the most confident
            point per pixel cell of each view (the density the views see), or "voxel", the most
            confident point per voxel (uniform in space).
        covisibility_rel_tol: relative depth tolerance of the co-visibility pruning (0.03).
        consistency_rel_tol: a dense point that other views see but none confirms within this relative
            depth (0.05) is dropped (`mvgeo.align.scene.covisibility_keep`; 0: off).
        free_space_rel_tol: a dense point another view sees through (its depth there more than this
            fraction (0.05) farther) is dropped (0: off).
        bundle_adjust: refine poses and focal(s) by sparse bundle adjustment on the pairs' inlier
            matches after the global alignment (True; needs a model that returns matches).
        bundle: options of the bundle adjustment.
        seed: RANSAC seed.
        loop_check: reject verified pairs whose relative rotation contradicts most of the loops of
            three pairs they take part in (`mvgeo.align.loops`: false pairs from repeated structure),
            before the alignment; align.json `pairs_rejected_by_loops`.
        max_loop_deg: a loop of three pairs is consistent below this rotation error.
        allow_partial: when the pair graph is disconnected, or views fail the checks above, register
            the largest group that passes (at least 2 views) and list the others in align.json
            `unregistered`, instead of failing with an error that names them (False).
        native_threads: OpenBLAS and OpenCV threads while aligning (1; restored afterwards; 0 keeps the
            settings): the pairwise stage is already parallel over pairs (`pairwise.workers`).
        dense_stereo: the output cloud's depth maps are recomputed with the final cameras
            (`mvgeo.align.dense_stereo`); off, they are the global alignment's, rescaled onto the
            bundle-adjusted tracks.
        refocus_min_change: without known intrinsics, when the bundle adjustment moves the shared focal
            by more than this absolute log change (0.1, about 10 %) from the one the pairs were computed
            with, the pairs' poses and pointmaps are computed again with the adjusted focal (same
            features and matches) and the alignment runs once more; align.json `focal_reestimation`.
            Two-view focal estimates are poor for narrow fields of view (DTU). 0: off.
        init_fallback: when the result from the default initialisation (DUSt3R's chaining of the
            pointmaps) contradicts its pairs as a whole (`max_unexplained_fraction`), solve once more
            from the pairs' own relative poses (`GlobalAlignConfig.init="pair_poses"`) and keep that
            only if it explains every verified pair with none dropped; align.json `init_fallback`.
        average_rotations: that second start takes its rotations from robust rotation averaging over
            every verified pair (`mvgeo.align.rotation_averaging`) instead of the spanning tree's, so a
            ring's drift is spread over all pairs (True).
        hole_fill: with the dense stereo, wide holes of a view's depth map (textureless surfaces) are
            filled by harmonic interpolation of the inverse depth, at low confidence
            (`mvgeo.align.hole_fill`); align.json `dense_stereo.fraction_filled`.
    """

    max_size_px: int = 640
    pairs: PairGraphSpec = field(default_factory=PairGraphSpec)
    pairwise: ClassicalPairConfig = field(default_factory=ClassicalPairConfig)
    align: GlobalAlignConfig = field(default_factory=lambda: GlobalAlignConfig(iters=100, pixel_stride=4))
    min_conf: float = 2.0
    consistency_px: float = 2.0
    min_pair_explained: float = 0.5
    max_unexplained_fraction: float = 0.1
    max_pair_rotation_deg: float = DEFAULT_MAX_LOOP_DEG
    max_focal_log_std: float = 0.05
    max_centre_std_ratio: float = 1.0
    reject_unsupported_views: bool = True
    points_budget: int = 200_000
    downsample: str = "pixel"
    covisibility_rel_tol: float = 0.03
    consistency_rel_tol: float = 0.05
    free_space_rel_tol: float = 0.05
    bundle_adjust: bool = True
    bundle: BundleConfig = field(default_factory=BundleConfig)
    seed: int = 0
    loop_check: bool = True
    max_loop_deg: float = DEFAULT_MAX_LOOP_DEG
    allow_partial: bool = False
    native_threads: int = 1
    dense_stereo: DenseStereoConfig = field(default_factory=DenseStereoConfig)
    refocus_min_change: float = 0.1
    init_fallback: bool = True
    average_rotations: bool = True
    hole_fill: HoleFillConfig = field(default_factory=HoleFillConfig)


#: A faster preset for tests and previews (fewer iterations, smaller pointmaps, at most 20k points).
PREVIEW = AlignConfig(max_size_px=320, pairwise=ClassicalPairConfig(pointmap_size_px=96),
                      align=GlobalAlignConfig(iters=60, pixel_stride=4), points_budget=20_000)


@dataclass
class AlignResult:
    """Output of `align_images`.

    Attributes:
        sparse_model: PINHOLE cameras at the input resolution, `cam_from_world`
            per image (names as given), and the output point cloud.
        points_xyz: (P, 3) float64 world points.
        points_rgb: (P, 3) uint8 colours.
        points_conf: (P,) float32 confidences (>= min_conf).
        stats: JSON-ready report (timings, losses, focals, failed pairs, ...).
    """

    sparse_model: SparseModel
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    points_conf: np.ndarray
    stats: dict


def _load(images: Sequence[Path] | Sequence[np.ndarray], names: Sequence[str] | None
          ) -> tuple[list[np.ndarray], list[str]]:
    if len(images) < 2:
        raise InputError(f"need at least 2 images, got {len(images)}", fix="add more views of the scene")
    if all(isinstance(x, (str, Path)) for x in images):
        paths = [Path(x) for x in images]
        arrays = [read_image(p) for p in paths]
        names = list(names) if names is not None else [p.name for p in paths]
    else:
        arrays = [np.asarray(x, np.float32) for x in images]
        names = list(names) if names is not None else [f"{k:03d}.png" for k in range(len(arrays))]
        paths = [Path(n) for n in names]
    if len(set(names)) != len(names):
        raise InputError("image names are not unique")
    sizes = {a.shape[:2] for a in arrays}
    if len(sizes) > 1:
        listing = ", ".join(f"{n}: {a.shape[1]}x{a.shape[0]}" for n, a in zip(names, arrays, strict=True))
        raise InputError(f"images have different sizes ({listing})",
                         fix="mvgeo align assumes one camera: resize/crop all images to one size first")
    seen: dict[str, str] = {}
    for n, a in zip(names, arrays, strict=True):
        h = hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()
        if h in seen:
            raise InputError(f"images {seen[h]!r} and {n!r} are identical (duplicate views carry no geometry)",
                             path=paths[names.index(n)], fix="remove one of them")
        seen[h] = n
    return arrays, names


def align_images(images: Sequence[Path] | Sequence[np.ndarray], config: AlignConfig = AlignConfig(), *,
                 names: Sequence[str] | None = None, intrinsics: Camera | None = None,
                 model: PointmapModel | None = None) -> AlignResult:
    """Pose-free reconstruction of a few views: pairwise pointmaps + DUSt3R global alignment.

    Args:
        images: image files, or (H, W, 3) float32 RGB arrays in [0, 1], all the same size.
        config: `AlignConfig`.
        names: image names for the output (default: file names, or 000.png, ...).
        intrinsics: known camera (at the input size, any supported model):
            images are undistorted and the focal is fixed instead of estimated.
        model: a `PointmapModel` (default: `ClassicalPointmapModel`).

    Returns:
        `AlignResult`.

    Raises:
        InputError: too few/corrupt/duplicate/mixed-size images, a disconnected
            pair graph (names the images that could not be connected).
        DegenerateGeometryError: the alignment failed numerically.
    """
    with native_threads(config.native_threads):
        return _align_images(images, config, names=names, intrinsics=intrinsics, model=model)


def _align_images(images, config: AlignConfig, *, names, intrinsics, model) -> AlignResult:
    if config.downsample not in ("pixel", "voxel"):
        raise ConfigError(f"unknown value {config.downsample!r}", key="downsample", expected="'pixel' or 'voxel'")
    timer = StageTimer()
    with timer.stage("load"):
        arrays, names = _load(images, names)
        all_names = list(names)
        H0, W0 = arrays[0].shape[:2]
        if intrinsics is not None:
            if (intrinsics.width, intrinsics.height) != (W0, H0):
                raise InputError(f"intrinsics are for {intrinsics.width}x{intrinsics.height} images, "
                                 f"the images are {W0}x{H0}", fix="pass the calibration of these images")
            arrays = [undistort_image(a, intrinsics) for a in arrays]
        s = min(1.0, config.max_size_px / max(H0, W0))
        Ha, Wa = max(1, round(H0 * s)), max(1, round(W0 * s))
        small = [a if (Ha, Wa) == (H0, W0) else cv2.resize(a, (Wa, Ha), interpolation=cv2.INTER_AREA) for a in arrays]
    n = len(arrays)
    K_align = None
    if intrinsics is not None:
        K = intrinsics.K.copy()
        K[0] *= Wa / W0
        K[1] *= Ha / H0
        K_align = np.repeat(K[None], n, axis=0)
    default_model = model is None
    if model is None:
        model = ClassicalPointmapModel(config.pairwise, K_align=K_align, seed=config.seed)
    pairs = make_pairs(n, config.pairs)
    solve = dict(arrays=arrays, small=small, names=names, K_align=K_align, intrinsics=intrinsics, model=model,
                 pairs=pairs, timer=timer, size0_wh=(W0, H0), refocus=default_model)
    sol, err, refocus = _solve_and_refocus(config=config, **solve)
    init_fallback = None
    if (err is not None and config.init_fallback and config.align.init == "procrustes"
            and _mostly_unexplained(sol, config)):
        # DUSt3R's Procrustes chaining can turn a view far from every one of its pairs (measured: one view of
        # N2V-denoised llff_like photos 117 deg off although each pair's own rotation was within 3 deg); the
        # pairs' own relative poses do not compound that way. Tried only when the result as a whole contradicts
        # its pairs: a wrong minimum that another start may avoid. One view its pairs do not support, or do not
        # pin, is weak data that another start does not fix (measured on a 28-view orbit: from the pair poses
        # it passed the checks bent by 8 deg).
        _log.warning("the alignment from the chained pointmaps is inconsistent with its pairs; trying again from "
                     "the pairs' own relative poses")
        init_fallback = {"tried": "pair_poses", "first_error": str(err)[:300]}
        alt_config = replace(config, align=replace(config.align, init="pair_poses"))
        try:
            # From the pairs as the first start left them: with the focal re-estimation's focal when it ran
            # (the second start then does not re-estimate from the prior again).
            alt_sol, alt_err, alt_refocus = _solve_and_refocus(config=alt_config, **{**solve, "model": sol.model})
        except (InputError, DegenerateGeometryError) as exc:
            init_fallback["kept"] = f"procrustes (pair_poses failed: {str(exc)[:300]})"
        else:
            # A result chosen after the fact needs more than the default's threshold: every verified pair
            # explained, none dropped (measured: from the pair poses temple_sparse_ring --allow-partial passed
            # the threshold at 7.8 deg after dropping one pair; the denoised llff_like photos: 0 of 30 pairs
            # inconsistent, none dropped).
            if alt_err is None and not alt_sol.bad and not alt_sol.dropped:
                sol, err, refocus = alt_sol, None, alt_refocus
                init_fallback["kept"] = "pair_poses"
            else:
                init_fallback["kept"] = ("procrustes (from pair_poses the result does not explain every verified "
                                         "pair either)")
        _log.info("initialisation fallback: kept %s", init_fallback["kept"])
    if err is not None:
        raise err
    model, arrays, small, names, n = sol.model, sol.arrays, sol.small, sol.names, len(sol.names)
    preds, matches, res, ba, ba_stats = sol.preds, sol.matches, sol.res, sol.ba, sol.ba_stats
    checks, bad, align_cfg, s_pm, Hp, Wp = sol.checks, sol.bad, sol.align_cfg, sol.s_pm, sol.Hp, sol.Wp
    failed_pairs, rejected, unregistered, dropped = sol.failed_pairs, sol.rejected, sol.unregistered, sol.dropped
    stereo_stats = None
    if config.dense_stereo.enabled:
        with timer.stage("dense_stereo"):
            K_a = np.stack([np.array([[f, 0, Wa / 2.0], [0, f, Ha / 2.0], [0, 0, 1]]) for f in res.focal_px * s_pm])
            stereo = stereo_depths(small, K_a, res.cam_from_world, [(p.i, p.j) for p in preds],
                                   {(i, j): uv for i, j, uv in matches}, config.dense_stereo)
        depth_maps, conf_maps, K_grid = list(stereo.depth), list(stereo.conf), list(stereo.K)
        # A view the stereo leaves (almost) empty (e.g. no baseline to any partner) keeps the global
        # alignment's depth map, resampled onto the stereo grid (same field of view).
        from_alignment = []
        for v, d in enumerate(depth_maps):
            if np.isfinite(d).mean() < config.dense_stereo.min_coverage:
                Hg, Wg = d.shape
                depth_maps[v] = cv2.resize(np.asarray(res.depth[v], np.float64), (Wg, Hg),
                                           interpolation=cv2.INTER_NEAREST)
                conf_maps[v] = cv2.resize(np.asarray(res.conf[v], np.float64), (Wg, Hg),
                                          interpolation=cv2.INTER_NEAREST)
                from_alignment.append(names[v])
        with timer.stage("hole_fill"):
            depth_maps, conf_maps, filled = fill_depth_holes(depth_maps, conf_maps, config.hole_fill)
        pts_maps = [backproject_depth(d, k, T) for d, k, T in zip(depth_maps, K_grid, res.cam_from_world,
                                                                    strict=True)]
        stereo_stats = {"size_wh": [int(depth_maps[0].shape[1]), int(depth_maps[0].shape[0])],
                        "n_pairs": len(preds),
                        "fraction_with_depth": [round(float(np.isfinite(d).mean()), 4) for d in stereo.depth],
                        "fraction_filled": [round(float(m.mean()), 4) for m in filled],
                        "views_with_alignment_depth": from_alignment}
        if ba is not None and ba.track_xyz is not None and len(ba.obs_view):
            # Agreement with the bundle-adjusted tracks (same cameras): median track / stereo depth per view.
            grid = np.array([depth_maps[0].shape[1] / Wa, depth_maps[0].shape[0] / Ha])
            ratio, spread = depth_rescale([np.nan_to_num(d, nan=-1.0) for d in depth_maps], res.cam_from_world,
                                          ba.track_xyz, ba.obs_view, ba.obs_point, ba.obs_uv * grid)
            stereo_stats["track_depth_ratio"] = [round(float(k), 4) for k in ratio]
            stereo_stats["track_log_mad"] = [None if np.isnan(m) else round(float(m), 4) for m in spread]
    else:
        depth_maps, conf_maps, pts_maps = res.depth, res.conf, res.pts_world
        K_grid = [np.array([[f, 0, Wp / 2.0], [0, f, Hp / 2.0], [0, 0, 1]]) for f in res.focal_px]
    with timer.stage("scene"):
        keep = covisibility_keep(pts_maps, depth_maps, conf_maps, res.cam_from_world, K_grid,
                                 rel_depth_tol=config.covisibility_rel_tol,
                                 consistency_rel_tol=config.consistency_rel_tol,
                                 free_space_rel_tol=config.free_space_rel_tol)
        xyz, rgb, conf, pix = [], [], [], []
        for v in range(n):
            Hg, Wg = depth_maps[v].shape
            col = cv2.resize(arrays[v], (Wg, Hg), interpolation=cv2.INTER_AREA)
            m = keep[v] & (conf_maps[v] > config.min_conf) & np.isfinite(depth_maps[v])
            xyz.append(pts_maps[v][m])
            rgb.append(np.clip(np.rint(col[m] * 255), 0, 255).astype(np.uint8))
            conf.append(conf_maps[v][m])
            rows, cols = np.nonzero(m)
            pix.append(np.stack([np.full(len(rows), v), rows, cols], axis=1))
        xyz, rgb, conf = np.concatenate(xyz), np.concatenate(rgb), np.concatenate(conf).astype(np.float32)
        pix = np.concatenate(pix)
        if config.downsample == "pixel":
            sel = pixel_downsample_by_confidence(pix[:, 0], pix[:, 1], pix[:, 2], conf, config.points_budget)
        else:
            sel = voxel_downsample_by_confidence(xyz, conf, config.points_budget)
        xyz, rgb, conf = xyz[sel], rgb[sel], conf[sel]
    cameras, posed = {}, []
    # One camera for all views when their intrinsics are one (known, or one shared focal), as COLMAP's
    # single-camera mode writes them; else one camera per view.
    one_camera = intrinsics is not None or bool(np.all(res.focal_px == res.focal_px[0]))
    for v in range(n):
        if intrinsics is not None:
            cam = Camera.pinhole(intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, W0, H0)
        else:
            f = float(res.focal_px[v])
            cam = Camera.pinhole(f * W0 / Wp, f * H0 / Hp, W0 / 2.0, H0 / 2.0, W0, H0)
        cam_id = 1 if one_camera else v + 1
        cameras.setdefault(cam_id, cam)
        posed.append(PosedImage(names[v], cam_id, res.cam_from_world[v]))
    sparse = SparseModel(cameras, posed, xyz, rgb)
    rejected_names = [(all_names[i], all_names[j], b, g) for (i, j), b, g in rejected]
    stats = {
        "n_images": len(all_names),
        "n_registered": n,
        "input_size_wh": [W0, H0],
        "align_size_wh": [Wa, Ha],
        "pointmap_size_wh": [Wp, Hp],
        "n_pairs": len(pairs),
        "n_pairs_ok": len(preds),
        "n_pairs_sparse": len(getattr(model, "sparse_matches", None) or []),
        "failed_pairs": failed_pairs,
        "pairs_rejected_by_loops": [{"i": u, "j": v, "inconsistent_loops": b, "consistent_loops": g}
                                    for u, v, b, g in rejected_names],
        "unregistered": unregistered,
        "iterations": align_cfg.iters,
        "init_loss": res.init_loss,
        "final_loss": res.final_loss,
        "focal_px": {im.name: cameras[im.camera_id].fx for im in posed},
        "known_intrinsics": intrinsics is not None,
        "shared_focal": align_cfg.shared_focal,
        "bundle_adjustment": ba_stats,
        "dense_stereo": stereo_stats,
        "focal_determined_by_pairs": bool(getattr(model, "focal_determined", True)),
        "focal_reestimation": refocus,
        "init_fallback": init_fallback,
        "sift_fallback_used": bool(getattr(model, "sift_fallback_used", False)),
        "pairs_dropped_as_inconsistent": [list(d) for d in dropped],
        "pair_consistency_min": min((c.explained_fraction for c in checks), default=float("nan")),
        "pairs_inconsistent": [[names[c.i], names[c.j], round(c.explained_fraction, 3),
                                None if np.isnan(c.rotation_deviation_deg) else round(c.rotation_deviation_deg, 2)]
                               for c in bad],
        "n_points": int(len(xyz)),
        "mean_confidence": float(conf.mean()) if len(conf) else float("nan"),
        "timings_s": timer.as_dict(),
        "config": _jsonable(asdict(config)),
    }
    return AlignResult(sparse, xyz, rgb, conf, stats)


def _solve_and_refocus(*, arrays, small, names, K_align, intrinsics, model, pairs, config: AlignConfig,
                       timer: StageTimer, size0_wh, refocus: bool):
    """`_solve`, then (see `AlignConfig.refocus_min_change`) once more with the bundle adjustment's focal when
    it moved far from the pairs'; returns (solution, its consistency error or None, align.json
    `focal_reestimation` or None). `refocus` False: the model is not the classical one (no second pass)."""
    sol = _solve(arrays, small, names, K_align, intrinsics, model, pairs, config, timer, size0_wh)
    err = _consistency_error(sol, config)
    refocus_report = None
    f_pairs = getattr(model, "focal_px_used", None)
    if (intrinsics is None and refocus and config.refocus_min_change > 0 and sol.ba is not None
            and f_pairs is not None):
        f_ba = float(np.median(sol.res.focal_px)) * sol.s_pm
        refocus_report = {"pairs_focal_px": round(f_pairs, 2), "bundle_focal_px": round(f_ba, 2), "refocused": False}
        if abs(np.log(f_ba / f_pairs)) > config.refocus_min_change:
            # The pairs' relative poses and pointmaps were computed with a focal the bundle adjustment
            # moved far: compute them again with its estimate (same features and matches).
            _log.warning("the bundle adjustment moved the focal from %.1f to %.1f px: computing the pairs again "
                         "with it", f_pairs, f_ba)
            refocus_report["refocused"] = True
            try:
                again = _solve(arrays, small, names, None, None, model.refocused(f_ba, len(arrays)), pairs, config,
                               timer, size0_wh)
            except (InputError, DegenerateGeometryError) as exc:
                refocus_report["kept"] = f"first pass (the second failed: {str(exc)[:300]})"
            else:
                err_again = _consistency_error(again, config)
                if err is None and err_again is not None:
                    refocus_report["kept"] = "first pass (the second is inconsistent with its pairs)"
                else:
                    sol, err, refocus_report["kept"] = again, err_again, "second pass"
            _log.info("focal re-estimation: kept the %s", refocus_report["kept"])
    return sol, err, refocus_report


@dataclass
class _Solution:
    """One pass of the pairs, the global alignment and the bundle adjustment (see `_solve`).

    The per-view lists hold the registered views only (`allow_partial` may drop some).
    """

    model: PointmapModel
    arrays: list[np.ndarray]
    small: list[np.ndarray]
    names: list[str]
    preds: list[PairPrediction]
    matches: list[tuple[int, int, np.ndarray]]
    res: GlobalAlignResult
    ba: BundleResult | None
    ba_stats: dict | None
    checks: list[PairCheck]
    bad: list[PairCheck]
    align_cfg: GlobalAlignConfig
    s_pm: float
    Hp: int
    Wp: int
    failed_pairs: list
    rejected: list
    unregistered: list
    dropped: list
    focal_determined: bool
    focal_undetermined_why: str = ""


def _solve(arrays, small, names, K_align, intrinsics, model, pairs, config: AlignConfig, timer: StageTimer,
           size0_wh) -> _Solution:
    """Pairs -> loop check -> global alignment -> bundle adjustment -> per-pair checks (not yet enforced).

    Raises:
        InputError: a disconnected pair graph (without `allow_partial`).
    """
    W0, H0 = size0_wh
    Ha, Wa = small[0].shape[:2]
    n = len(arrays)
    with timer.stage("pairwise"):
        preds, fails = model.predict_pairs(small, pairs)
    Hp, Wp = pointmap_shape(Ha, Wa, model.pointmap_size_px)
    s_pm = Wa / Wp
    # Every verified pair's matches when the model has them (the classical one computes dense
    # pointmaps for a subset of the pairs only), else those of the predictions.
    matches = getattr(model, "sparse_matches", None) or [(p.i, p.j, p.matches_px) for p in preds
                                                         if p.matches_px is not None]
    failed_pairs = [{"i": names[f.i], "j": names[f.j], "reason": f.reason} for f in fails]
    rejected = []
    if config.loop_check and preds:
        with timer.stage("loop_check"):
            preds, matches, rejected = _loop_check(preds, matches, K_align, s_pm, n, config)
        failed_pairs += [{"i": names[i], "j": names[j], "reason": (
            f"rejected: its relative rotation contradicts {bad} of the {bad + good} loops of three pairs it is in")}
            for (i, j), bad, good in rejected]
        fails = fails + [PairFailure(i, j, "rejected by the loop check") for (i, j), _, _ in rejected]
    unregistered = []
    keep = _connected_views(n, names, preds, fails, allow_partial=config.allow_partial)
    if len(keep) < n:
        unregistered = [{"name": names[v], "reason": "not connected to the registered images by any usable pair"}
                        for v in range(n) if v not in keep]
        _log.warning("registering %d of %d images (--allow-partial); not connected: %s", len(keep), n,
                     [u["name"] for u in unregistered])
        arrays, small, names, preds, matches, K_align = _restrict(keep, arrays, small, names, preds, matches, K_align)
        n = len(keep)
    sizes = [(Hp, Wp)] * n
    align_cfg = config.align
    focal_init = None
    if intrinsics is not None:
        # Known calibration: fx at the pointmap grid (square pixels assumed by the alignment).
        focal_init = np.full(n, 0.5 * (intrinsics.fx * Wp / W0 + intrinsics.fy * Hp / H0))
        align_cfg = replace(align_cfg, optimize_focal=False)
    all_matches = matches
    dropped: list[tuple[str, str]] = []
    # One retry without the inconsistent pairs; with allow_partial, up to two more, each time keeping
    # the largest group of images the remaining pairs connect.
    attempts = 4 if config.allow_partial else 2
    for attempt in range(attempts):
        sizes = [(Hp, Wp)] * n
        if intrinsics is not None:
            focal_init = np.full(n, 0.5 * (intrinsics.fx * Wp / W0 + intrinsics.fy * Hp / H0))
        with timer.stage("global_align"):
            init = (_averaged_rotation_init(preds, matches, sizes, focal_init, align_cfg, s_pm, (Wa, Ha))
                    if config.average_rotations and align_cfg.init == "pair_poses" else None)
            res = global_align(preds, sizes, config=align_cfg, focal_init_px=focal_init, init=init)
        ba, ba_stats = None, None
        if config.bundle_adjust and matches:
            with timer.stage("bundle_adjust"):
                ba_cfg = replace(config.bundle, shared_focal=config.bundle.shared_focal or align_cfg.shared_focal,
                                 optimize_focal=intrinsics is None)
                ba = bundle_adjust(res.cam_from_world, res.focal_px * s_pm, (Wa, Ha), matches, config=ba_cfg)
                res, depth_scales = _reposed(res, ba.cam_from_world, ba.focal_px / s_pm, ba, s_pm)
                ba_stats = {k: v for k, v in asdict(ba).items()
                            if k not in ("cam_from_world", "focal_px", "track_xyz", "obs_view", "obs_point", "obs_uv",
                                         "centre_std")}
                ba_stats["centre_std_ratio"] = _centre_std_ratio(ba)
                ba_stats["dense_depth_rescale"] = depth_scales
        # Without the bundle adjustment the poses come from pointmaps s_pm times coarser than the
        # matches: judge them at that resolution.
        thr = config.consistency_px * (1.0 if ba is not None else max(s_pm, 1.0))
        checks, bad = _judge(res, s_pm, (Wa, Ha), matches, thr, config)
        loose = _loose_views(ba, config)
        if config.allow_partial and loose and attempt < attempts - 1:
            # Views the tracks do not pin (see `max_centre_std_ratio`): register the others, solve again.
            # The largest group the other views' pairs connect (the loose views are singletons here).
            keep = components(n, [(p.i, p.j) for p in preds if p.i not in loose and p.j not in loose])[0]
            if len(keep) >= 2:
                why = {v: "its position is not determined by the feature tracks" for v in loose}
                _log.warning("allow_partial: keeping %d of %d images; the positions of %s are not determined by "
                             "the feature tracks", len(keep), n, [names[v] for v in loose])
                *lists, all_matches, lost = _drop_views(
                    keep, lambda v, why=why: why.get(v, "not connected to the others once the views with "
                                                        "undetermined positions are removed"),
                    arrays, small, names, preds, matches, K_align, all_matches)
                arrays, small, names, preds, matches, K_align = lists
                unregistered += lost
                n = len(keep)
                continue
        if not bad or attempt == attempts - 1:
            break
        # Retry without the pairs the reconstruction does not explain (e.g. symmetric
        # structure matched across the object): they may have bent the solution.
        gone = {(c.i, c.j) for c in bad}
        kept = [p for p in preds if (p.i, p.j) not in gone]
        comps = components(n, [(p.i, p.j) for p in kept])
        if len(comps) > 1 and not (config.allow_partial and len(comps[0]) >= 2):
            break  # dropping them would cut views off: judge (and fail) this result as it is
        dropped += sorted((names[i], names[j]) for i, j in gone)
        _log.warning("%d verified pairs are inconsistent with the reconstruction %s; solving again without them",
                     len(gone), sorted(gone))
        preds = kept
        matches = [m for m in matches if (m[0], m[1]) not in gone]
        if len(comps) > 1:
            keep = comps[0]
            *lists, all_matches, lost = _drop_views(
                keep, lambda v: "its pairs are inconsistent with the reconstruction of the others",
                arrays, small, names, preds, matches, K_align, all_matches)
            arrays, small, names, preds, matches, K_align = lists
            _log.warning("allow_partial: keeping %d of %d images; %s lost their consistent pairs", len(keep), n,
                         [u["name"] for u in lost])
            unregistered += lost
            n = len(keep)
    if dropped:  # judge the final result against all the evidence, the dropped pairs included
        checks, bad = _judge(res, s_pm, (Wa, Ha), all_matches, thr, config)
    return _Solution(model, arrays, small, names, preds, matches, res, ba, ba_stats, checks, bad, align_cfg, s_pm,
                     Hp, Wp, failed_pairs, rejected, unregistered, dropped,
                     focal_determined=getattr(model, "focal_determined", True) or intrinsics is not None,
                     focal_undetermined_why=getattr(model, "focal_undetermined_why", ""))


def _averaged_rotation_init(preds, matches, sizes, focal_init, align_cfg: GlobalAlignConfig, s_pm: float, size_wh):
    """`init_from_averaged_rotations` at the alignment's initial focals; None (the plain pair-pose chaining)
    where the pairs with a rotation do not connect the views or the chaining fails."""
    f = focal_init if focal_init is not None else focal_estimates(preds, len(sizes))
    if focal_init is None and align_cfg.shared_focal:
        f = np.full(len(sizes), float(np.exp(np.mean(np.log(f)))))
    try:
        return init_from_averaged_rotations(preds, matches, sizes, np.asarray(f, float), s_pm, size_wh)
    except DegenerateGeometryError as exc:
        _log.warning("rotation averaging gave no initialisation (%s); chaining the pairs' own poses", exc)
        return None


def _reposed(res, cam_from_world: np.ndarray, focal_px: np.ndarray, ba=None, s_pm: float = 1.0):
    """The alignment result with new poses/focals; dense points re-projected from the depth maps.

    The bundle adjustment fixes only view 0's pose, so its scene can come out at another scale than the
    global alignment's (and each view's focal can change): depth maps kept as they were would no longer
    agree with the new cameras, and the dense cloud would be smeared across views. With `ba`'s tracks,
    each view's depth map is rescaled by the median ratio of the refined track depths to the map's
    depths at the same pixels (`s_pm` = alignment pixels per pointmap pixel).

    Returns:
        (result, per-view depth scales with their robust spread, or None without tracks).
    """
    depths = [np.asarray(d, float) for d in res.depth]
    report = None
    if ba is not None and ba.track_xyz is not None and len(ba.obs_view):
        scales, spreads = depth_rescale(depths, cam_from_world, ba.track_xyz, ba.obs_view, ba.obs_point,
                                        ba.obs_uv / s_pm)
        depths = [d * k for d, k in zip(depths, scales, strict=True)]
        report = {"scale": [round(float(k), 4) for k in scales],
                  "log_mad": [None if np.isnan(m) else round(float(m), 4) for m in spreads]}
    pts = []
    for v, d in enumerate(depths):
        H, W = d.shape
        R, t = cam_from_world[v][:, :3], cam_from_world[v][:, 3]
        pts.append(((pixel_rays(H, W, float(focal_px[v])) * d[..., None]) - t) @ R)
    out = replace(res, cam_from_world=cam_from_world, focal_px=np.asarray(focal_px, float), pts_world=pts,
                  depth=depths)
    return out, report


def backproject_depth(depth: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
    """(H, W, 3) world points of a z-depth map (NaN stays NaN); K (3, 3) in our pixel convention."""
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    x = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1) * depth[..., None]
    return (x - cam_from_world[:, 3]) @ cam_from_world[:, :3]


def depth_rescale(depths: Sequence[np.ndarray], cam_from_world: np.ndarray, track_xyz: np.ndarray,
                  obs_view: np.ndarray, obs_point: np.ndarray, obs_uv_px: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per-view scale that brings each depth map onto triangulated tracks.

    Args:
        depths: N (H, W) z-depth maps.
        cam_from_world: (N, 3, 4) the cameras the tracks were triangulated with.
        track_xyz: (P, 3) world points; obs_view, obs_point: (K,) observation -> view, point.
        obs_uv_px: (K, 2) observed pixels in the depth maps' own pixel grid (corner origin).

    Returns:
        scales (N,): median over the view's observations of track depth / map depth (1 where a view has
        fewer than 5 usable observations); log_mad (N,): median absolute deviation of the log ratios
        (how well one scale explains the view; nan where unused).
    """
    n = len(depths)
    scales, spreads = np.ones(n), np.full(n, np.nan)
    for v in range(n):
        sel = np.flatnonzero(obs_view == v)
        if len(sel) == 0:
            continue
        H, W = depths[v].shape
        z_track = track_xyz[obs_point[sel]] @ cam_from_world[v][2, :3] + cam_from_world[v][2, 3]
        col = np.clip(np.floor(obs_uv_px[sel, 0]).astype(int), 0, W - 1)
        row = np.clip(np.floor(obs_uv_px[sel, 1]).astype(int), 0, H - 1)
        z_map = depths[v][row, col]
        ok = (z_track > 0) & (z_map > 0) & np.isfinite(z_map)
        if ok.sum() < 5:
            continue
        log_ratio = np.log(z_track[ok] / z_map[ok])
        med = float(np.median(log_ratio))
        scales[v], spreads[v] = np.exp(med), float(np.median(np.abs(log_ratio - med)))
    return scales, spreads


def _judge(res, s_pm: float, size_wh, matches, thr: float, config: AlignConfig):
    """Per pair: Sampson check, and the rotation check (`pair_rotation_deviation`); the failing pairs.

    A pair fails when it explains too few of its matches, or when the result's relative rotation is more
    than `max_pair_rotation_deg` off the one its matches imply under the final focal.
    """
    if not matches:
        return [], []
    f = res.focal_px * s_pm
    checks = pair_consistency(res.cam_from_world, f, size_wh, matches, threshold_px=thr)
    if config.max_pair_rotation_deg > 0:
        dev = pair_rotation_deviation(res.cam_from_world, f, size_wh, matches)
        checks = [replace(c, rotation_deviation_deg=d) for c, d in zip(checks, dev, strict=True)]
    bad = [c for c in checks if c.explained_fraction < config.min_pair_explained
           or (config.max_pair_rotation_deg > 0 and c.rotation_deviation_deg > config.max_pair_rotation_deg)]
    return checks, bad


def _mostly_unexplained(sol: _Solution, config: AlignConfig) -> bool:
    """The inconsistent pairs hold more than `max_unexplained_fraction` of all verified matches: the result as
    a whole is wrong (not one weakly linked view)."""
    total = sum(c.n_matches for c in sol.checks)
    return bool(total) and sum(c.n_matches for c in sol.bad) > config.max_unexplained_fraction * total


def _consistency_error(sol: _Solution, config: AlignConfig) -> DegenerateGeometryError | None:
    """The specific error of a result the evidence contradicts, or None."""
    checks, bad, names, focal_determined, ba = sol.checks, sol.bad, sol.names, sol.focal_determined, sol.ba
    total = sum(c.n_matches for c in checks)
    unexplained = sum(c.n_matches for c in bad)
    if _mostly_unexplained(sol, config):
        listing = ", ".join(f"({names[c.i]}, {names[c.j]}): {c.explained_fraction:.0%}"
                            + (f" rotation {c.rotation_deviation_deg:.0f} deg off its matches"
                               if c.rotation_deviation_deg > config.max_pair_rotation_deg else "")
                            for c in bad)[:1500]
        return DegenerateGeometryError(
            f"the reconstruction is inconsistent with {len(bad)} of {len(checks)} verified image pairs "
            f"({unexplained} of {total} matches unexplained; explained fraction per pair, and the rotation "
            f"where the result turns the pair more than {config.max_pair_rotation_deg:g} deg away from the one "
            f"its matches imply: {listing}). "
            "Likely causes: too little overlap between neighbouring views (e.g. an orbit with large "
            "steps), repeated or symmetric structure matched across the scene"
            + ("" if focal_determined else ", and no image pair determines the focal length")
            + (". The bundle adjustment is off: the dense alignment alone is this coarse; enable it (--ba)"
               if ba is None else ". Add views between the existing ones, or pass --intrinsics"))
    orphans = views_without_consistent_pair(checks, bad, len(names)) if config.reject_unsupported_views else []
    if orphans:
        def pairs_of(v):
            return "; ".join(f"with {names[c.j if c.i == v else c.i]}: {c.explained_fraction:.0%} explained"
                             + (f", rotation {c.rotation_deviation_deg:.0f} deg off"
                                if c.rotation_deviation_deg > config.max_pair_rotation_deg else "")
                             for c in bad if v in (c.i, c.j))
        listing = ", ".join(f"{names[v]} ({pairs_of(v)})" for v in orphans)[:1500]
        return DegenerateGeometryError(
            f"the reconstruction contradicts every verified image pair of {len(orphans)} of {len(names)} views, "
            f"so their poses are not supported by their matches: {listing}. Likely causes: too little overlap "
            "between these views and their neighbours (e.g. an orbit with large steps), or repeated or symmetric "
            "structure matched across the scene. Add views between the existing ones, or pass --allow-partial "
            "to register the others")
    loose = _loose_views(ba, config)
    if loose:
        ratio = _centre_std_ratio(ba)
        listing = ", ".join(f"{names[v]} ({ratio[v]:.2g})" for v in loose)[:1500]
        return DegenerateGeometryError(
            f"the positions of {len(loose)} of {len(ratio)} views are not determined by the feature tracks: "
            f"their camera centres are uncertain by more than {config.max_centre_std_ratio:g} times the "
            f"median distance between neighbouring cameras (standard deviation / that distance: {listing}). "
            "Likely cause: these views are linked to the others by tracks seen in two views only, so each "
            "pair fixes a direction but not a distance (e.g. an orbit with large steps). Add views between "
            "the existing ones, or pass --allow-partial to register the others")
    if not focal_determined and ba is not None and ba.focal_log_std > config.max_focal_log_std:
        why = f": {sol.focal_undetermined_why}" if sol.focal_undetermined_why else ""
        return DegenerateGeometryError(
            f"the focal length is not determined by these views (no image pair determines it{why}; and the "
            f"bundle adjustment leaves a relative uncertainty of {ba.focal_log_std:.0%}). Pass the calibration "
            "with --intrinsics, or add views with more parallax")
    return None


def _loose_views(ba: BundleResult | None, config: AlignConfig) -> list[int]:
    """Views whose centre uncertainty ratio (`_centre_std_ratio`) exceeds `max_centre_std_ratio`."""
    ratio = _centre_std_ratio(ba) if ba is not None else None
    if ratio is None or config.max_centre_std_ratio <= 0:
        return []
    return [v for v, q in enumerate(ratio) if q > config.max_centre_std_ratio]


def _centre_std_ratio(ba: BundleResult) -> list[float] | None:
    """Per view, the largest standard deviation of its camera centre over the median distance from each
    camera to its nearest neighbour; None without the estimate (scipy solver) or with fewer than 3 views
    (with two, holding one camera leaves the other's distance free: that is the scale gauge, not a defect)."""
    if ba.centre_std is None or len(ba.centre_std) < 3:
        return None
    R, t = ba.cam_from_world[:, :, :3], ba.cam_from_world[:, :, 3]
    C = -np.einsum("nji,nj->ni", R, t)
    d = np.linalg.norm(C[:, None] - C[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    scale = float(np.median(d.min(axis=1)))
    if not scale > 0:
        return [float("inf")] * len(C)
    return [round(float(s) / scale, 4) for s in ba.centre_std]


def _drop_views(keep: list[int], reason, arrays, small, names, preds, matches, K_align, all_matches):
    """`_restrict` to `keep`, with `all_matches` renumbered too; returns the six restricted lists, then
    `all_matches`, then the align.json `unregistered` entries of the other views (`reason(view) -> str`)."""
    lost = [{"name": names[v], "reason": reason(v)} for v in range(len(names)) if v not in keep]
    new = {v: k for k, v in enumerate(keep)}
    all_matches = [(new[i], new[j], uv) for i, j, uv in all_matches if i in new and j in new]
    return (*_restrict(keep, arrays, small, names, preds, matches, K_align), all_matches, lost)


def _restrict(keep: list[int], arrays, small, names, preds, matches, K_align):
    """Keep only the views `keep` (renumbered in that order) in every per-view and per-pair list."""
    new = {v: k for k, v in enumerate(keep)}
    preds = [replace(p, i=new[p.i], j=new[p.j]) for p in preds if p.i in new and p.j in new]
    matches = [(new[i], new[j], uv) for i, j, uv in matches if i in new and j in new]
    return ([arrays[v] for v in keep], [small[v] for v in keep], [names[v] for v in keep], preds, matches,
            None if K_align is None else K_align[keep])


def _loop_check(preds, matches, K_align, s_pm: float, n: int, config: AlignConfig):
    """Drop the pairs `reject_by_loops` finds; returns (preds, matches, [((i, j), n_bad, n_good)])."""
    if K_align is None:  # the pairs' focal estimates, pointmap pixels -> alignment pixels
        H2, W2 = preds[0].pts_i.shape[:2]
        f = focal_estimates(preds, n) * s_pm
        c = np.array([W2 * s_pm / 2.0, H2 * s_pm / 2.0])
        K_align = np.array([[[fv, 0, c[0]], [0, fv, c[1]], [0, 0, 1]] for fv in f])
    rel, weight = pair_rotations(matches, K_align, preds)
    loop = reject_by_loops(rel, weight, max_loop_deg=config.max_loop_deg)
    if not loop.removed:
        return preds, matches, []
    gone = set(loop.removed)
    _log.warning("loop check: %d of %d loops of three pairs are inconsistent; rejected pairs %s",
                 loop.n_inconsistent, loop.n_triangles, sorted(gone))
    key = lambda i, j: (min(i, j), max(i, j))  # noqa: E731
    preds = [p for p in preds if key(p.i, p.j) not in gone]
    matches = [m for m in matches if key(m[0], m[1]) not in gone]
    return preds, matches, [(e, b, g) for e, (b, g) in zip(loop.removed, loop.votes, strict=True)]


def _connected_views(n: int, names: list[str], preds, fails: list[PairFailure], *, allow_partial: bool) -> list[int]:
    """The views to register: all (connected graph), the largest group (`allow_partial`), or an InputError."""
    comps = components(n, [(p.i, p.j) for p in preds])
    if len(comps) == 1:
        return comps[0]
    main = comps[0]
    if allow_partial and len(main) >= 2:
        return main
    lost = [names[v] for c in comps[1:] for v in c]
    reasons = "; ".join(f"({names[f.i]}, {names[f.j]}): {f.reason}" for f in fails
                        if (f.i in main) != (f.j in main))[:2000]
    raise InputError(
        f"the pair graph is disconnected: images {lost} could not be related to {[names[v] for v in main]}"
        + (f". Failed pairs: {reasons}" if reasons else ""),
        fix=("no two images could be related: check that they show one scene with enough overlap and texture"
             if len(main) < 2 else "add views that overlap the disconnected ones, or remove them; try --pairs "
             "complete; or pass --allow-partial to register only the largest connected group"))


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (bool, int, float, str)) or x is None:
        return x
    return str(x)


def write_align_result(out: str | Path | OutputPlan, result: AlignResult, *, overwrite: bool = False) -> Path:
    """Write `OUT/sparse/0/*.bin`, `OUT/points.ply` and `OUT/align.json` atomically.

    Args:
        out: the folder, or the plan `prepare_output(..., command="mvgeo align")` made for it.
        result: from `align_images`.
        overwrite: a previous `mvgeo align` output at `out` may be replaced (anything else is refused,
            see `mvgeo.common.output`).

    Returns:
        The folder written.

    Raises:
        InputError: `out` is refused by the output policy.
    """
    plan = as_output_plan(out, command="mvgeo align", overwrite=overwrite)
    with atomic_output_dir(plan) as tmp:
        write_sparse_model(tmp / "sparse" / "0", result.sparse_model, binary=True)
        write_points_ply(tmp / "points.ply", result.points_xyz, result.points_rgb, result.points_conf)
        (tmp / "align.json").write_text(json.dumps(result.stats, indent=2, allow_nan=True))
    return plan.out


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, conf: np.ndarray) -> None:
    """Binary PLY: x y z float32, red green blue uint8, confidence float32 (Open3D reads it)."""
    from plyfile import PlyData, PlyElement

    arr = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1"), ("confidence", "f4")])
    arr["x"], arr["y"], arr["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    arr["red"], arr["green"], arr["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    arr["confidence"] = conf
    PlyData([PlyElement.describe(arr, "vertex")], text=False).write(str(path))


__all__ = ["AlignConfig", "AlignResult", "PREVIEW", "align_images", "write_align_result"]
