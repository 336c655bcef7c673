"""The default `PointmapModel`: classical, weight-free pairwise pointmaps.

For each pair (i, j):

1. SIFT (OpenCV) on the alignment-resolution images, mutual nearest
   neighbours with Lowe's ratio test;
2. robust relative pose: `mvgeo.twoview.estimate_relative_pose_uncalibrated`
   (shared unknown focal, principal point at the centre) or, with known
   intrinsics, the calibrated `estimate_relative_pose`;
3. dense correspondences at the pointmap resolution: the inlier matches are
   densified with OpenCV's edge-aware interpolator (EpicFlow) and refined by
   DIS optical flow, both ways, keeping pixels that pass a forward-backward
   check and lie near their epipolar line;
4. triangulation of every kept pixel (`mvgeo.triangulate.triangulate_two_view`,
   cheirality, triangulation angle, angular error);
5. confidence = 1 + `conf_max` * forward-backward term * angle term * epipolar
   term, so 1 means "unknown" (those pixels get a placeholder depth, the
   median along the ray, and zero weight in the alignment).

Pointmaps are in camera i's frame with the pair's baseline as unit length.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from mvgeo.align.dense_pairs import pair_flows, pair_pointmap, quarter_turns
from mvgeo.align.features import MatchSet, detect_and_match, extract_features, match_features
from mvgeo.align.graph import components, maximum_spanning_tree
from mvgeo.align.pair_focal import consensus_focal, why_no_focal
from mvgeo.align.pairs import PairFailure, PairGeometry, PairPrediction, PairSet
from mvgeo.common.deps import cv2
from mvgeo.common.errors import DegenerateGeometryError
from mvgeo.common.progress import progress, progress_bar
from mvgeo.common.threads import pool_threads
from mvgeo.transforms import skew
from mvgeo.triangulate import TriangulationCriteria
from mvgeo.twoview import TwoViewConfig, estimate_relative_pose, estimate_relative_pose_uncalibrated

__all__ = ["ClassicalPairConfig", "ClassicalPointmapModel", "extract_features", "match_features", "pointmap_shape",
           "select_dense_pairs"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClassicalPairConfig:
    """Options of the classical pair estimator.

    Attributes:
        pointmap_size_px: long side of the pointmaps (and of the depth maps the
            global alignment optimises). 128 px: 12 views at ~12k pixels each;
            the poses come from the sparse bundle adjustment, so this only sets
            the density of the output cloud (and the dense stage's cost).
        sift_features: SIFT keypoints per image (at the alignment resolution).
        sift_blur_sigma_px: Gaussian blur before SIFT (pixels at the alignment
            resolution); 1 px doubled the matches on the noisy synthetic scenes.
        sift_contrast_threshold: OpenCV's `contrastThreshold` (its default 0.04;
            OpenCV divides it by the 3 layers per octave, so it is COLMAP's
            `peak_threshold` 0.0067 x 3 x 2: OpenCV's default keeps half the contrast range).
        fallback_sift: when the putative-match graph is disconnected, detect and
            match once more with COLMAP-like sensitivity (`fallback_contrast_threshold`,
            no pre-blur) and keep the matches of whichever run connects more images.
            On the dark, low-texture temple_sparse_ring (12 of its views at 512 px) the
            default SIFT finds ~420 keypoints per image and its correct pairs leave the ring
            in 5 pieces; contrast 0.02 without blur ~1060 keypoints, 2 pieces; contrast 0.01
            ~1300 keypoints (~1750 at 640 px), one piece (docs/bench/real.md). It is
            not the default because the blur helps on noisy images and more keypoints
            cost quadratic matching time.
        fallback_contrast_threshold: see `fallback_sift`.
        fallback_min_inliers: the relative-pose inlier minimum in the fallback run.
            12, as in the default run (`two_view`'s): the weak pairs that close
            temple_sparse_ring's ring have 21-24 inliers. The wrong pairs the weaker
            keypoints admit (on temple, one of 17 inliers, 51 deg off; measured at a floor of 15)
            are left to the loop check and the per-pair checks after the alignment, which need
            accurate pair poses: hence `fallback_refine`.
        fallback_refine: the fallback run refines each pair's relative pose on its inliers
            (`TwoViewConfig.refine`, also the default run's setting). On temple_sparse_ring (known
            intrinsics, 640 px, contrast 0.01) the correct pairs' unrefined USAC_MAGSAC rotations were
            0.2-7.2 deg off (median 2.6 deg; the pairs within 5 deg of the truth formed two pieces); refined,
            0.06-1.9 deg (median 0.42 deg, one piece).
        fallback_blur_sigma_px: see `fallback_sift`.
        sensitive_below_noise: images whose median estimated noise (`features.estimate_noise_sigma`, gray,
            [0, 1] units) is below this are detected with the fallback's COLMAP-like settings from the start
            (0: never). Clean DTU scan24 (2.1/255), at a 15-inlier floor: 40 verified pairs instead of 30,
            0.25 deg median rotation error, max 0.60, ATE 0.0067 (default detection 0.27, 0.74, 0.0084); clean temple
            (0.4/255) gets the result its fallback gave, without the first detection. N2V-denoised photos
            (4.5/255) keep the default detection: with the COLMAP-like one, one of three was 1.0 deg off
            (0.30 with the default).
        focal_prior: without well-determined pair focals, the shared focal is
            `focal_prior * max(W, H)` (COLMAP's default prior, 1.2).
        ratio: Lowe's ratio test threshold.
        min_matches: fewer putative matches -> the pair fails.
        two_view: options of the relative-pose estimators (RANSAC threshold in
            pixels at the alignment resolution). At least 12 inliers at the 1 px Sampson threshold
            (COLMAP: 15 at a 4 px epipolar threshold): the verified-pair graph is then as dense as
            pycolmap's exhaustive matching on clean DTU scan24 (43 pairs, 40 with 15 inliers) with the same
            accuracy, and on six sigma-25 draws 28-33 pairs (26-31 with 15) with the mean median / max
            rotation error 0.377 / 0.924 deg and ATE 0.0120 (0.394 / 0.943, 0.0122); temple and the
            synthetic orbit unchanged; the loop check rejects 0-1 more pair per set. Also lowering
            `min_matches` to 15 refused the synthetic orbit (`benchmarks/diag_match_density.py
            m20_i15,base,m15_i12 6`, docs/bench/real.md). Default backend: OpenCV's
            USAC_MAGSAC (measured ~40x faster than our numpy LO-MSAC, same
            accuracy; ``backend="own"`` selects ours), followed by the LM refinement
            of each pair's pose on its inliers and the re-selection of the inliers
            (`TwoViewConfig.refine`): the inliers are the bundle adjustment's
            tracks, and USAC's own model can be several degrees off on weak pairs
            (DTU scan24 with sigma 25 noise, noise seed 2: one view's three pairs
            6-28 deg off, the view placed 2.8 deg off; refined, mean over six noise
            seeds 0.37 deg median rotation error against 0.45 unrefined, mean max
            0.96 against 1.41 deg; docs/bench/real.md). On object_ring with 28
            training views the refined pairs register all views (0.57 deg) where
            the unrefined ones leave view_001 unsupported.
        focal_pairs: the shared focal is found from at most this many pairs (those with the most matches).
        focal_min_agreeing: the pairs determine the focal only where at least this many of their
            well-determined focals (all the pairs tried, if fewer) agree within `focal_agree_log`
            (`consensus_focal`). A single pair's focal can pass the well-determined test far from the truth
            on real photos: on DTU scan24 (truth 925 px at 384 px) single pairs gave 369, 398, 274, 153 and
            139 px, the last accepted as the shared focal and confirmed by a bundle adjustment at 142 px, a
            model 26 deg off that explained 95 % of the matches. On llff_like the ten pairs' focals lie
            within 9 % of their median.
        focal_agree_log: the agreement tolerance of `focal_min_agreeing`, |log(f / median)|.
        workers: threads for SIFT, matching, relative poses and dense
            pointmaps (0: the caller's, `mvgeo.common.threads.pool_threads`: one per core by default,
            as pycolmap's; one on a one-CPU Ray task).
        dense_top_k: dense pointmaps only for each view's `dense_top_k` pairs
            with the most inliers (plus a spanning tree that keeps the graph
            connected); 0: every pair (DUSt3R's complete graph). The sparse
            matches of *every* verified pair still feed the bundle adjustment
            (`PairSet.geometries`). On llff_like 12 views, 4 (~30 of 66 pairs)
            halved the pairwise time without changing the final pose error.
        fb_max_px: forward-backward consistency limit, pixels at the pointmap resolution.
        epipolar_max_px: Sampson distance limit of a dense match, pointmap pixels.
        angle_ref_deg: triangulation angle at which the angle term saturates to 1.
        conf_max: confidence of a perfect pixel is 1 + conf_max.
        triangulation: validity criteria of the dense triangulation.
    """

    pointmap_size_px: int = 128
    sift_features: int = 4000
    sift_blur_sigma_px: float = 1.0
    sift_contrast_threshold: float = 0.04
    fallback_sift: bool = True
    fallback_contrast_threshold: float = 0.01
    fallback_blur_sigma_px: float = 0.0
    sensitive_below_noise: float = 3.0 / 255.0
    fallback_min_inliers: int = 12
    fallback_refine: bool = True
    focal_prior: float = 1.2
    ratio: float = 0.8
    min_matches: int = 20
    two_view: TwoViewConfig = field(default_factory=lambda: TwoViewConfig(backend="opencv", refine=True,
                                                                          min_inliers=12))
    focal_pairs: int = 10
    focal_min_agreeing: int = 3
    focal_agree_log: float = 0.15
    workers: int = 0
    dense_top_k: int = 4
    fb_max_px: float = 1.0
    epipolar_max_px: float = 1.5
    angle_ref_deg: float = 5.0
    conf_max: float = 10.0
    triangulation: TriangulationCriteria = field(
        default_factory=lambda: TriangulationCriteria(min_angle_deg=0.5, max_angular_error_deg=2.0))


def pointmap_shape(height: int, width: int, long_side_px: int) -> tuple[int, int]:
    """(H, W) of the pointmap grid for an image, long side `long_side_px` (never upsampled)."""
    s = min(1.0, long_side_px / max(height, width))
    return max(1, round(height * s)), max(1, round(width * s))


def select_dense_pairs(n: int, inliers: dict[tuple[int, int], int], top_k: int) -> list[tuple[int, int]]:
    """Pairs that get dense pointmaps: each view's `top_k` pairs with most inliers, plus a maximum
    spanning tree of the inlier counts (connectivity); `top_k <= 0` takes every pair. Strongest first."""
    keys = sorted(inliers, key=lambda k: -inliers[k])
    if top_k <= 0:
        return keys
    chosen = set()
    for v in range(n):
        mine = [k for k in keys if v in k][:top_k]
        chosen.update(mine)
    tree = maximum_spanning_tree(n, keys, [float(inliers[k]) + 1.0 for k in keys])
    chosen.update(keys[e] for e in tree)
    return [k for k in keys if k in chosen]



def _gray_u8(image: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(np.ascontiguousarray(image, dtype=np.float32), cv2.COLOR_RGB2GRAY)
    return np.clip(np.rint(g * 255.0), 0, 255).astype(np.uint8)


def _resize(image: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    if image.shape[:2] == hw:
        return image
    return cv2.resize(image, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)


class DensePairError(Exception):
    """A verified pair whose dense pointmap failed (reported as a `PairFailure`, never raised to users)."""


class ClassicalPointmapModel:
    """SIFT + two-view geometry + dense flow + triangulation as a `PointmapModel` (a `RefocusableModel`).

    Two stages: `match` (features and putative matches, once per image and pair; `mvgeo.align.features`)
    and `relate` (relative poses at one focal, dense pointmaps: the `PairSet`). `predict_pairs` runs both;
    `refocus` runs `relate` again at another focal on the same matches.

    Args:
        config: `ClassicalPairConfig`.
        K_align: optional known intrinsics per image, (N, 3, 3) at the alignment
            resolution (undistorted images); None estimates a shared focal from the pairs.
        seed: RANSAC seed (deterministic results).
        focal_prior_px: without `K_align`, the shared focal (alignment pixels) the pairs start at, e.g. the
            photos' EXIF focal (`mvgeo.align.intrinsics.exif_focal_prior`): the pair focals' consensus is
            then not computed. None: the consensus, else `ClassicalPairConfig.focal_prior`.
    """

    def __init__(self, config: ClassicalPairConfig = ClassicalPairConfig(), *, K_align: np.ndarray | None = None,
                 seed: int = 0, focal_prior_px: float | None = None):
        if focal_prior_px is not None and not (np.isfinite(focal_prior_px) and focal_prior_px > 0):
            raise ValueError(f"focal_prior_px must be a positive number of pixels, got {focal_prior_px}")
        self.config = config
        self.K_align = None if K_align is None else np.asarray(K_align, np.float64)
        self.seed = seed
        self.focal_prior_px = None if focal_prior_px is None else float(focal_prior_px)
        self._matched: tuple[tuple, MatchSet] | None = None  # (images and pairs key, MatchSet) of the last `match`
        # Dense flows of the last `relate`, by their exact inputs (`_dense_pairs`): a refocused `relate` reuses the
        # flows of every pair whose inliers did not change (DTU scan24: 21 of 28 pairs, temple: 31 of 38).
        self._flow_cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def pointmap_size_px(self) -> int:
        return self.config.pointmap_size_px

    def _pool(self) -> ThreadPoolExecutor:
        # Threads: OpenCV and BLAS release the GIL; every task is independent and deterministic,
        # and results are collected in submission order.
        return ThreadPoolExecutor(max_workers=pool_threads(self.config.workers))

    def match(self, images: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]]) -> MatchSet:
        """Features and putative matches (`mvgeo.align.features.detect_and_match`); computed once for the
        same images and pairs (the key hashes the images)."""
        digest = hashlib.sha1()
        for im in images:
            digest.update(np.ascontiguousarray(im).tobytes())
        key = (digest.hexdigest(), tuple(pairs))
        if self._matched is not None and self._matched[0] == key:
            return self._matched[1]
        with self._pool() as pool:
            ms = detect_and_match(images, pairs, self.config, pool)
        self._matched = (key, ms)
        return ms

    def predict_pairs(self, images: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]]) -> PairSet:
        """`relate(images, match(images, pairs))`: every pair; failures come back with reasons."""
        return self.relate(images, self.match(images, pairs))

    def refocus(self, images: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]], focal_px: float) -> PairSet:
        """The pair geometry again at the shared focal `focal_px` (alignment pixels, principal point at the
        centre), from the same features and matches. `focal_determined` is the caller's to carry over."""
        H, W = images[0].shape[:2]
        K = np.array([[focal_px, 0.0, W / 2.0], [0.0, focal_px, H / 2.0], [0.0, 0.0, 1.0]])
        return self.relate(images, self.match(images, pairs), np.repeat(K[None], len(images), axis=0))

    def relate(self, images: Sequence[np.ndarray], ms: MatchSet, K_align: np.ndarray | None = None) -> PairSet:
        """Relative poses and dense pointmaps of the matched pairs.

        Without intrinsics (`K_align` here, else the model's), the focal is found first (InstantSplat's
        focal averaging, done before the alignment): every pair's shared-focal relative pose, then the
        focal the *well-determined* pair focals agree on (`RelativePoseResult.focal_well_determined`,
        `consensus_focal`; object-centric rings are a critical configuration for two-view focal estimation)
        becomes one calibration for the calibrated relative pose of every pair. With `focal_prior_px` (the
        photos' EXIF focal) that focal is used instead, without the pair focals.

        Args:
            images: N images (H, W, 3) float32 RGB at the alignment resolution.
            ms: their `MatchSet`.
            K_align: (N, 3, 3) intrinsics at the alignment resolution, or None.
        """
        cfg = self.config
        two_view = cfg.two_view
        if ms.sensitive:
            two_view = replace(two_view, min_inliers=max(two_view.min_inliers, cfg.fallback_min_inliers),
                               refine=two_view.refine or cfg.fallback_refine)
        K = self.K_align if K_align is None else np.asarray(K_align, np.float64)
        determined, why, prior_px = True, "", None
        with self._pool() as pool:
            if K is None and self.focal_prior_px is not None:
                f, determined, prior_px = self.focal_prior_px, False, self.focal_prior_px
                why = ("the pairs started at the focal length prior (the photos' EXIF focal, or the one given), "
                       "and the bundle adjustment moved the focal away from it")
                _log.info("shared focal %.1f px: the focal length prior", f)
            elif K is None:
                f, determined, why = self.shared_focal(images, ms, pool)
            if K is None:
                Ha, Wa = images[0].shape[:2]
                K = np.repeat(np.array([[[f, 0, Wa / 2.0], [0, f, Ha / 2.0], [0, 0, 1]]]), len(images), axis=0)
            rels, fails = self._relative_poses(ms, K, two_view, pool)
            geometries = [PairGeometry(i, j, np.concatenate([u1[r.inlier_mask], u2[r.inlier_mask]], axis=1),
                                       np.concatenate([r.R, r.t.reshape(3, 1)], axis=1))
                          for (i, j), (r, u1, u2) in rels.items()]
            preds, dense_fails = self._dense_pairs(images, K, rels, pool)
        return PairSet(preds, sorted(list(ms.failures) + fails + dense_fails, key=lambda f: (f.i, f.j)), geometries,
                       focal_determined=determined, focal_px=float(np.median(K[:, 0, 0])),
                       focal_undetermined_why=why, sensitive_features=ms.sensitive,
                       focal_prior_px=prior_px, features=tuple(ms.features))

    def _relative_poses(self, ms: MatchSet, K: np.ndarray, two_view: TwoViewConfig, pool: Executor):
        def relative(ij):
            u1, u2 = ms.pixels(*ij)
            try:
                return estimate_relative_pose(u1, u2, K[ij[0]], K[ij[1]], config=two_view), u1, u2
            except cv2.error as exc:  # USAC asserts on some degenerate inputs (measured at 256 px)
                return f"OpenCV robust estimation failed: {str(exc).strip().splitlines()[-1][:200]}", u1, u2

        rels, fails = {}, []
        for (i, j), (rel, u1, u2) in zip(ms.matches, pool.map(relative, list(ms.matches)), strict=True):
            if isinstance(rel, str):
                fails.append(PairFailure(i, j, rel))
            elif rel.success:
                rels[(i, j)] = (rel, u1, u2)
            else:
                fails.append(PairFailure(i, j, f"relative pose: {rel.reason}"))
        return rels, fails

    def _dense_pairs(self, images, K, rels, pool: Executor) -> tuple[list[PairPrediction], list[PairFailure]]:
        """Dense pointmaps for `select_dense_pairs`; a failed one is replaced by the best pair bridging the cut."""
        small = [_gray_u8(_resize(im, pointmap_shape(im.shape[0], im.shape[1], self.config.pointmap_size_px)))
                 for im in images]
        order = select_dense_pairs(len(images), {k: v[0].n_inliers for k, v in rels.items()}, self.config.dense_top_k)
        preds, fails, done = [], [], set()
        digests = [hashlib.sha1(g.tobytes()).hexdigest() + str(g.shape) for g in small]
        previous, self._flow_cache = self._flow_cache, {}

        def flows(i, j, a, b, R):
            """`pair_flows` of pair (i, j), from the previous `relate` when its inputs are the same."""
            key = (digests[i], digests[j], a.tobytes(), b.tobytes(), quarter_turns(R))
            out = previous.get(key)
            if out is None:
                out = pair_flows(small[i], small[j], a, b, R)
            self._flow_cache[key] = out
            return out

        def dense(ij):
            try:
                return self._dense(images, small, K, *ij, *rels[ij], flows=flows)
            except (DensePairError, DegenerateGeometryError) as exc:
                return exc

        with progress_bar(total=len(order), desc="pairwise pointmaps") as bar:
            while order:
                for (i, j), out in zip(order, pool.map(dense, order), strict=True):
                    done.add((i, j))
                    bar.update(1)
                    if isinstance(out, PairPrediction):
                        preds.append(out)
                    else:
                        fails.append(PairFailure(i, j, str(out)))
                        _log.debug("pair (%d, %d) failed: %s", i, j, out)
                # A failed dense pair may have cut the graph: add the best bridging pair.
                comps = components(len(images), [(p.i, p.j) for p in preds])
                label = {v: c for c, vs in enumerate(comps) for v in vs}
                bridge = sorted((k for k in rels if k not in done and label[k[0]] != label[k[1]]),
                                key=lambda k: -rels[k][0].n_inliers)
                order = bridge[:1]
        return preds, fails

    def shared_focal(self, images, ms: MatchSet, pool: Executor | None = None) -> tuple[float, bool, str]:
        """(focal in alignment pixels, whether pairs determined it, why not): the focal the well-determined
        pair focals of the `focal_pairs` pairs with the most matches agree on (`consensus_focal`), or the
        prior."""
        Ha, Wa = images[0].shape[:2]
        best = sorted(ms.matches, key=lambda ij: -len(ms.matches[ij]))[:self.config.focal_pairs]

        def one(ij):
            u1, u2 = ms.pixels(*ij)
            try:
                return estimate_relative_pose_uncalibrated(u1, u2, (Wa, Ha), config=self.config.two_view,
                                                           seed=self.seed)
            except cv2.error:  # USAC assertion on a degenerate sample set: this pair gives no focal
                return None

        rels = list(progress((pool.map if pool else map)(one, best), desc="pair focals", total=len(best)))
        focals = [float(r.focal_px) for r in rels if r is not None and r.success and r.focal_well_determined]
        f = consensus_focal(focals, len(rels), self.config.focal_min_agreeing, self.config.focal_agree_log)
        if f is not None:
            _log.info("shared focal %.1f px (the agreeing of %d well-determined pairs of %d)", f, len(focals),
                      len(rels))
            return f, True, ""
        f = self.config.focal_prior * max(Wa, Ha)
        _log.warning("no pair determines the focal length; using the prior %.2f * max(W, H) = %.1f px",
                     self.config.focal_prior, f)
        return f, False, why_no_focal(rels, self.config.two_view)

    def _dense(self, images, small, K_align, i: int, j: int, rel, u1, u2, *, flows=None) -> PairPrediction:
        """Pair (i, j)'s pointmaps; `flows(i, j, a, b, R)` returns its flows (default `pair_flows`)."""
        # Everything below works on the pointmap grid.
        Hi, Wi = small[i].shape
        Hj, Wj = small[j].shape
        if Hi != Hj or Wi != Wj:
            raise DensePairError("images of different sizes are not supported by the dense matcher")
        si, sj = Wi / images[i].shape[1], Wj / images[j].shape[1]
        Ki, Kj = K_align[i].copy(), K_align[j].copy()
        Ki[:2] *= si
        Kj[:2] *= sj
        inl = rel.inlier_mask
        a, b = u1[inl] * si, u2[inl] * sj
        R, t = rel.R, rel.t  # cam_j_from_cam_i, |t| = 1
        flow_ij, flow_ji = (pair_flows(small[i], small[j], a, b, R) if flows is None else flows(i, j, a, b, R))
        F = np.linalg.inv(Kj).T @ skew(t) @ R @ np.linalg.inv(Ki)
        cam_j_from_i = np.concatenate([R, t.reshape(3, 1)], axis=1)
        cam_i_from_j = np.concatenate([R.T, (-R.T @ t).reshape(3, 1)], axis=1)
        pts_i, conf_i = pair_pointmap(flow_ij, flow_ji, Ki, Kj, F, cam_j_from_i, self.config)
        pts_j_in_j, conf_j = pair_pointmap(flow_ji, flow_ij, Kj, Ki, F.T, cam_i_from_j, self.config)
        pts_j = pts_j_in_j @ R - (R.T @ t)  # R^T (x_j - t)
        n_ok = int(np.count_nonzero(conf_i > 1) + np.count_nonzero(conf_j > 1))
        if n_ok < 0.02 * (conf_i.size + conf_j.size):
            raise DensePairError(f"only {n_ok} dense pixels passed the consistency checks")
        return PairPrediction(i, j, pts_i.astype(np.float32), pts_j.astype(np.float32), conf_i.astype(np.float32),
                              conf_j.astype(np.float32), float(Ki[0, 0]), float(Kj[0, 0]),
                              matches_px=np.concatenate([u1[inl], u2[inl]], axis=1))
