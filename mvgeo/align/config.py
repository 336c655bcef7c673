"""`AlignConfig`: every option of `mvgeo.align.align_images`, and the `PREVIEW` preset."""

from __future__ import annotations

from dataclasses import dataclass, field

from mvgeo.align.bundle import BundleConfig
from mvgeo.align.classical_pairs import ClassicalPairConfig
from mvgeo.align.dense_stereo import DenseStereoConfig
from mvgeo.align.global_align import GlobalAlignConfig
from mvgeo.align.graph import PairGraphSpec
from mvgeo.align.hole_fill import HoleFillConfig
from mvgeo.align.loops import DEFAULT_MAX_LOOP_DEG
from mvgeo.common.errors import ConfigError

__all__ = ["DEFAULT", "AlignConfig", "PREVIEW"]

INITIAL_POSES = ("auto", "chain", "averaged")


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
            every 8th pixel row/column of the pointmaps (16 x 16 samples of a 128-pixel one), since the final
            poses come from the bundle adjustment: on the real sets the poses are those of every 4th to
            the printed digit, at about two thirds of the stage's time (docs/bench/align_speed.md).
        candidate_align_iters: global-alignment iterations each candidate runs before its bundle adjustment;
            None (default): all of `align.iters`. Fewer (0: the start's values go to the adjustment as they
            are) run the full alignment once, for the chosen candidate's cloud, only where the cloud uses
            its depth maps (`dense_stereo` off, or a view the stereo leaves empty). 0 gave the same or better
            poses on DTU scan24 (clean and sigma 25/255, six noise draws), the clean temple ring, llff_like
            and object_ring, 4-14 % faster (docs/bench/align_speed.md), but at sigma 50/255 the noisy DTU
            photos were refused on three seeds of three (0.75 deg with the iterations) and one seed's denoised
            photos were accepted 1.1 deg / ATE 0.18 off: a bent start needs the alignment before the
            adjustment.
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
        max_focal_log_std: without known intrinsics, without any pair that determines the focal and without a
            focal prior (EXIF) the adjustment keeps within `refocus_min_change`, the bundle adjustment must
            determine it: a log-focal standard deviation above this (0.05) fails the alignment.
        max_centre_std_ratio: a view whose camera centre the bundle adjustment leaves uncertain (largest
            standard deviation with the other cameras held, `mvgeo.align.bundle_lm.camera_centre_std`) by
            more than this fraction (1.0) of the median distance between neighbouring cameras fails the
            alignment, or with `allow_partial` is left out: the feature tracks do not determine its
            position. 0: off. Reported in align.json `bundle_adjustment.centre_std_ratio`.
        reject_unsupported_views: a view all of whose verified pairs are inconsistent with the result
            (`mvgeo.align.checks.views_cut_off`) fails the alignment, or with
            `allow_partial` is left out, whatever share of the matches its pairs hold (True).
        locate_cut_off_views: before refusing such views (with the bundle adjustment and a pair model with
            features), try to locate each by PnP on points the main group's explained pairs triangulate at
            the solution's poses (`mvgeo.align.locate`): a view PnP places within 3 deg of the solution
            (at least 15 inliers) is supported by three-view evidence its weak pairs could not give, and
            is kept; views PnP places confidently elsewhere are re-posed there and the candidate adjusted
            again (`mvgeo.align.solve.relocate`; not kept if that turns the other views' relative rotations
            by more than 3 deg). align.json `views_located_by_points`.
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
        seed: seed of the project's own RANSAC (`mvgeo.ransac`: the pairs' focal estimates and relative poses
            with `TwoViewConfig(backend="own")`). The default backend, OpenCV's USAC, draws with its own
            fixed seed, so with it the result does not depend on this value.
        loop_check: reject verified pairs whose relative rotation contradicts most of the loops of
            three pairs they take part in (`mvgeo.align.loops`: false pairs from repeated structure),
            before the alignment; align.json `pairs_rejected_by_loops`.
        max_loop_deg: a loop of three pairs is consistent below this rotation error.
        allow_partial: when the pair graph is disconnected, or views fail the checks above, register
            the largest group that passes (at least 2 views) and list the others in align.json
            `unregistered`, instead of failing with an error that names them (False). The group is
            judged by its own pairs only, fewer and often weaker: on the noisy DTU spread (12 views 20-40
            deg apart, which the defaults refuse) it registered 5.1 views per draw at 0.88 deg, but 3 of 10
            draws held views more than 5 deg off (docs/bench/real_partial_draws.md); over 24 view sets of
            the shared captures 4 held views more than 5 deg off, the noisy temple's 16 views all registered
            at 5.5 deg median, 21 deg max (docs/bench/real_subsets.md).
        native_threads: OpenBLAS and OpenCV threads while aligning (1; restored afterwards; 0 keeps the
            settings): the pairwise stage is already parallel over pairs (`pairwise.workers`).
        dense_stereo: the output cloud's depth maps are recomputed with the final cameras
            (`mvgeo.align.dense_stereo`); off, they are the global alignment's, rescaled onto the
            bundle-adjusted tracks.
        refocus_min_change: without known intrinsics, when a candidate's bundle adjustment moves the shared
            focal by more than this absolute log change (0.1, about 10 %) from the one its pairs were computed
            with, the pair geometry is computed again at the adjusted focal (same features and matches) and
            solved as another candidate (`mvgeo.align.policy`); two-view focal estimates are poor for narrow
            fields of view (DTU). 0: off.
        initial_poses: how a candidate's poses are initialised (`mvgeo.align.init`): "chain" (DUSt3R: the
            pairs' pointmaps chained along the maximum spanning tree by Procrustes), "averaged" (GLOMAP's
            approach: rotation averaging over every verified pair, then the camera centres by global
            positioning on the feature tracks; the pair-pose chaining where that fails) or "auto" (the
            stated rule, `mvgeo.align.init.choose_start`: chaining first, averaged second, unless the chained
            start contradicts most of the pairs' relative rotations).
        second_start: when a candidate contradicts its pairs as a whole (`max_unexplained_fraction`), or the
            first start's candidates are all refused, solve once more from the other initialisation and let
            the selection rule choose (True).
        max_candidates: at most this many candidate solutions (starts, focal re-estimations, prunings)
            per alignment (8).
        hole_fill: with the dense stereo, wide holes of a view's depth map (textureless surfaces) are
            filled by harmonic interpolation of the inverse depth, at low confidence
            (`mvgeo.align.hole_fill`); align.json `dense_stereo.fraction_filled`.
        exif_focal: without known intrinsics, image files whose EXIF carries one 35 mm-equivalent focal
            length (`mvgeo.align.intrinsics.exif_focal_prior`; every phone and most cameras write it) start the
            pairs at that focal instead of the pair focals' consensus or COLMAP's prior 1.2 max(W, H); the
            bundle adjustment still refines it, and re-estimates the pairs when it moves more than
            `refocus_min_change` (True). align.json `focal_prior`.
        principal_point: without known intrinsics, "auto" (default) estimates the principal point for the
            accepted solution and keeps it where the views determine it (`mvgeo.align.principal`: views around
            an object do, close views do not); "centre" keeps it at the image centre (COLMAP's default).
            align.json `principal_point`.
    """

    max_size_px: int = 640
    pairs: PairGraphSpec = field(default_factory=PairGraphSpec)
    pairwise: ClassicalPairConfig = field(default_factory=ClassicalPairConfig)
    align: GlobalAlignConfig = field(default_factory=lambda: GlobalAlignConfig(iters=100, pixel_stride=8))
    candidate_align_iters: int | None = None
    min_conf: float = 2.0
    consistency_px: float = 2.0
    min_pair_explained: float = 0.5
    max_unexplained_fraction: float = 0.1
    max_pair_rotation_deg: float = DEFAULT_MAX_LOOP_DEG
    max_focal_log_std: float = 0.05
    max_centre_std_ratio: float = 1.0
    reject_unsupported_views: bool = True
    locate_cut_off_views: bool = True
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
    initial_poses: str = "auto"
    second_start: bool = True
    max_candidates: int = 8
    hole_fill: HoleFillConfig = field(default_factory=HoleFillConfig)
    exif_focal: bool = True
    principal_point: str = "auto"

    def __post_init__(self) -> None:
        if self.principal_point not in ("auto", "centre"):
            raise ConfigError(f"unknown value {self.principal_point!r}", key="principal_point",
                              expected="'auto' or 'centre'")
        if self.bundle.refine_principal:  # its cameras, stereo and verdict would still assume the centre
            raise ConfigError("the alignment's candidates keep the principal point fixed",
                              key="bundle.refine_principal",
                              fix="leave it False; principal_point='auto' estimates it for the accepted result")
        if self.downsample not in ("pixel", "voxel"):
            raise ConfigError(f"unknown value {self.downsample!r}", key="downsample",
                              expected="'pixel' or 'voxel'")
        if self.initial_poses not in INITIAL_POSES:
            raise ConfigError(f"unknown value {self.initial_poses!r}", key="initial_poses",
                              expected=" or ".join(repr(s) for s in INITIAL_POSES))
        if self.max_candidates < 1:
            raise ConfigError(f"must be at least 1, got {self.max_candidates}", key="max_candidates")


#: A faster preset for tests and previews (fewer iterations, smaller pointmaps, at most 20k points).
PREVIEW = AlignConfig(max_size_px=320, pairwise=ClassicalPairConfig(pointmap_size_px=96),
                      align=GlobalAlignConfig(iters=60, pixel_stride=4), points_budget=20_000)

#: The defaults (`mvgeo align`'s).
DEFAULT = AlignConfig()
