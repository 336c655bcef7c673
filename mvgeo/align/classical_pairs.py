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

import logging
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from mvgeo.align.graph import components, maximum_spanning_tree
from mvgeo.align.pairs import PairFailure, PairPrediction
from mvgeo.common.deps import cv2
from mvgeo.common.errors import DegenerateGeometryError
from mvgeo.common.progress import progress, progress_bar
from mvgeo.epipolar import sampson_distance
from mvgeo.transforms import skew
from mvgeo.triangulate import TriangulationCriteria, triangulate_two_view
from mvgeo.twoview import TwoViewConfig, estimate_relative_pose, estimate_relative_pose_uncalibrated

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
            15, as in the default run (COLMAP's `min_num_inliers`): the weak pairs that
            close temple_sparse_ring's ring have 21-24 inliers. The wrong pairs the weaker
            keypoints admit (on temple, one of 17 inliers, 51 deg off) are left to the loop
            check and the per-pair checks after the alignment, which need accurate pair
            poses: hence `fallback_refine`.
        fallback_refine: the fallback run refines each pair's relative pose on its inliers
            (`TwoViewConfig.refine`). On temple_sparse_ring (known intrinsics, 640 px,
            contrast 0.01) the correct pairs' unrefined USAC_MAGSAC rotations were 0.2-7.2 deg
            off (median 2.6 deg; the pairs within 5 deg of the truth formed two pieces); refined,
            0.06-1.9 deg (median 0.42 deg, one piece). Not in the default run: on object_ring rendered with 32
            views (28 training views at 256x192) the refined pairs led to a bent result the
            checks passed (28/28, median relative rotation error 2.6 deg, max 26 deg, ATE
            0.34 m on the 3 m ring), where the unrefined ones are refused naming view_001.
        fallback_blur_sigma_px: see `fallback_sift`.
        focal_prior: without well-determined pair focals, the shared focal is
            `focal_prior * max(W, H)` (COLMAP's default prior, 1.2).
        ratio: Lowe's ratio test threshold.
        min_matches: fewer putative matches -> the pair fails.
        two_view: options of the relative-pose estimators (RANSAC threshold in
            pixels at the alignment resolution). Default backend: OpenCV's
            USAC_MAGSAC (measured ~40x faster than our numpy LO-MSAC, same
            accuracy; ``backend="own"`` selects ours), without the per-pair LM
            refinement in the default run (the bundle adjustment refines all poses
            jointly; see `fallback_refine` for the fallback run).
        focal_pairs: the shared focal is the median over at most this many
            pairs (those with the most matches).
        workers: threads for SIFT, matching, relative poses and dense
            pointmaps (0: one per CPU core, as pycolmap's default).
        dense_top_k: dense pointmaps only for each view's `dense_top_k` pairs
            with the most inliers (plus a spanning tree that keeps the graph
            connected); 0: every pair (DUSt3R's complete graph). The sparse
            matches of *every* verified pair still feed the bundle adjustment
            (`sparse_matches`). On llff_like 12 views, 4 (~30 of 66 pairs)
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
    fallback_min_inliers: int = 15
    fallback_refine: bool = True
    focal_prior: float = 1.2
    ratio: float = 0.8
    min_matches: int = 20
    two_view: TwoViewConfig = field(default_factory=lambda: TwoViewConfig(backend="opencv", refine=False))
    focal_pairs: int = 10
    workers: int = 0
    dense_top_k: int = 4
    fb_max_px: float = 1.0
    epipolar_max_px: float = 1.5
    angle_ref_deg: float = 5.0
    conf_max: float = 10.0
    triangulation: TriangulationCriteria = field(
        default_factory=lambda: TriangulationCriteria(min_angle_deg=0.5, max_angular_error_deg=2.0))


@dataclass
class ImageFeatures:
    """SIFT of one image. uv_px: (K, 2) our pixel convention; desc: (K, 128) float32."""

    uv_px: np.ndarray
    desc: np.ndarray
    _root: np.ndarray | None = field(default=None, repr=False)
    _root_t: np.ndarray | None = field(default=None, repr=False)

    def root(self) -> np.ndarray:
        """RootSIFT descriptors (computed once; every pair of this image reuses them)."""
        if self._root is None:
            self._root = _root_sift(self.desc)
        return self._root

    def root_t(self) -> np.ndarray:
        """(128, K) contiguous transpose of `root` (the right operand of the matching products)."""
        if self._root_t is None:
            self._root_t = np.ascontiguousarray(self.root().T)
        return self._root_t


def pointmap_shape(height: int, width: int, long_side_px: int) -> tuple[int, int]:
    """(H, W) of the pointmap grid for an image, long side `long_side_px` (never upsampled)."""
    s = min(1.0, long_side_px / max(height, width))
    return max(1, round(height * s)), max(1, round(width * s))


def _gray_u8(image: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(np.ascontiguousarray(image, dtype=np.float32), cv2.COLOR_RGB2GRAY)
    return np.clip(np.rint(g * 255.0), 0, 255).astype(np.uint8)


def extract_features(image: np.ndarray, *, n_features: int, blur_sigma_px: float = 0.0,
                     contrast_threshold: float = 0.04) -> ImageFeatures:
    """SIFT keypoints (converted to our pixel convention: OpenCV + 0.5) and descriptors."""
    sift = cv2.SIFT_create(nfeatures=n_features, contrastThreshold=contrast_threshold)
    gray = _gray_u8(image)
    if blur_sigma_px > 0:
        gray = cv2.GaussianBlur(gray, (0, 0), blur_sigma_px)
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or not kps:
        return ImageFeatures(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    uv = np.array([k.pt for k in kps], dtype=np.float64) + 0.5
    return ImageFeatures(uv, desc.astype(np.float32))


def match_features(a: ImageFeatures, b: ImageFeatures, *, ratio: float, block_rows: int = 256) -> np.ndarray:
    """(M, 2) index pairs: mutual nearest neighbours passing the ratio test both ways.

    RootSIFT (Arandjelovic & Zisserman 2012): descriptors are L1-normalised and
    square-rooted, so the squared Euclidean distance is ``2 - 2 a.b``; all
    distances come from BLAS products instead of k-NN searches
    (`match_features_reference` is the obvious loop it is tested against).

    The similarity matrix is formed `block_rows` rows of `a` at a time (a block
    stays in cache for the reductions; ~10 % faster than the whole matrix at
    2400 x 2300 keypoints, same matches). Per row: best column, its similarity and
    the runner-up. Per column only the maximum over the entries that are *not* some
    row's best is kept (`col_rest`); the rows' bests are grouped by column afterwards,
    which gives each column's best and runner-up exactly. A tie for a column's best
    (two rows with the same similarity) fails the column's ratio test, as in the
    reference.
    """
    if len(a.desc) < 2 or len(b.desc) < 2:
        return np.zeros((0, 2), np.int64)
    da, dbT = a.root(), b.root_t()
    Ka, Kb = len(da), dbT.shape[1]
    ab = np.empty(Ka, np.int64)  # row's best column
    s0 = np.empty(Ka, np.float32)  # row's best similarity (squared distance = 2 - 2 s)
    row_second = np.empty(Ka, np.float32)
    col_rest = np.full(Kb, -np.inf, np.float32)
    step = max(1, int(block_rows))
    for r in range(0, Ka, step):
        sim = da[r:r + step] @ dbT
        rows = np.arange(len(sim))
        best = np.argmax(sim, axis=1)
        ab[r:r + len(sim)] = best
        s0[r:r + len(sim)] = sim[rows, best]
        sim[rows, best] = -np.inf
        row_second[r:r + len(sim)] = np.max(sim, axis=1)
        np.maximum(col_rest, np.max(sim, axis=0), out=col_rest)
    # The two largest row-best similarities per column (rows sorted by column, then similarity).
    order = np.lexsort((-s0, ab))
    cols, sims = ab[order], s0[order]
    first = np.r_[True, cols[1:] != cols[:-1]]
    second = np.r_[False, first[:-1]] & ~first
    top1 = np.full(Kb, -np.inf, np.float32)
    top2 = np.full(Kb, -np.inf, np.float32)
    top1[cols[first]] = sims[first]
    top2[cols[second]] = sims[second]
    mutual = s0 >= np.maximum(col_rest, top1)[ab]
    col_second = np.maximum(col_rest, top2)[ab]  # for a mutual row: the best of the column's other entries

    def dist2(x):
        return np.maximum(2.0 - 2.0 * x, 0.0)

    r2 = ratio * ratio
    d0 = dist2(s0)
    ok = mutual & (d0 < r2 * dist2(row_second)) & (d0 < r2 * dist2(col_second))
    q = np.flatnonzero(ok)
    return np.stack([q, ab[q]], axis=1).astype(np.int64).reshape(-1, 2)


def match_features_reference(a: ImageFeatures, b: ImageFeatures, *, ratio: float) -> np.ndarray:
    """Slow, obvious version of `match_features` (loops; the tests' reference)."""
    da, db = _root_sift(a.desc).astype(np.float64), _root_sift(b.desc).astype(np.float64)

    def nn(x, y, k):
        d = np.sum((y - x[k]) ** 2, axis=1)
        o = np.argsort(d, kind="stable")
        return int(o[0]), d[o[0]] < ratio * ratio * d[o[1]]

    out = []
    for k in range(len(da)):
        j, ok = nn(da, db, k)
        if ok:
            k2, ok2 = nn(db, da, j)
            if ok2 and k2 == k:
                out.append((k, j))
    return np.array(out, np.int64).reshape(-1, 2)


def _root_sift(desc: np.ndarray) -> np.ndarray:
    d = np.abs(np.asarray(desc, np.float32))
    return np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))


def _resize(image: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    if image.shape[:2] == hw:
        return image
    return cv2.resize(image, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)


_MIN_INTERPOLATOR_MATCHES = 8


def dense_flow(gray_a: np.ndarray, gray_b: np.ndarray, uv_a_px: np.ndarray, uv_b_px: np.ndarray) -> np.ndarray:
    """(H, W, 2) flow a -> b: sparse matches densified (edge-aware), refined by DIS.

    Args:
        gray_a, gray_b: (H, W) uint8 images of the same size.
        uv_a_px, uv_b_px: (M, 2) matches in our pixel convention at this resolution.
    """
    H, W = gray_a.shape
    # OpenCV pixel centres sit at integers: ours - 0.5 (docs/conventions.md).
    src = (uv_a_px - 0.5).astype(np.float32)
    dst = (uv_b_px - 0.5).astype(np.float32)
    inside = (src[:, 0] >= 0) & (src[:, 0] <= W - 1) & (src[:, 1] >= 0) & (src[:, 1] <= H - 1)
    src, dst = src[inside], dst[inside]
    # OpenCV's EdgeAwareInterpolator segfaults (measured: 2 of 3 runs on a real pair) when two
    # matches fall on the same integer pixel (SIFT returns one keypoint per orientation, so exact
    # duplicates are common) or when it gets very few matches. Keep one match per pixel, and
    # below a handful fall back to the median displacement as the initial flow.
    _, first = np.unique(np.rint(src).astype(np.int64) @ np.array([1, W + 1]), return_index=True)
    src, dst = src[np.sort(first)], dst[np.sort(first)]
    if len(src) < _MIN_INTERPOLATOR_MATCHES:
        shift = np.median(dst - src, axis=0) if len(src) else np.zeros(2, np.float32)
        init = np.broadcast_to(shift.astype(np.float32), (H, W, 2))
    else:
        interp = cv2.ximgproc.createEdgeAwareInterpolator()
        interp.setK(min(32, len(src) - 1))
        init = interp.interpolate(cv2.cvtColor(gray_a, cv2.COLOR_GRAY2BGR), src.reshape(-1, 1, 2),
                                  cv2.cvtColor(gray_b, cv2.COLOR_GRAY2BGR), dst.reshape(-1, 1, 2))
    dis = cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(gray_a, gray_b, np.ascontiguousarray(init, dtype=np.float32))


def _flow_rotated_180(gray_a, gray_b, uv_a_px, uv_b_px) -> tuple[np.ndarray, np.ndarray]:
    """Flows a -> b and b -> a when b is turned upside down relative to a (in-plane rotation
    near 180 deg, e.g. a camera on the far side of a ring rig: DIS flow, which searches small
    displacements coarse to fine, finds nothing there). Flow against b rotated by 180 deg
    (pixel p -> (W, H) - p in our convention), then express both flows in b's own pixels."""
    H, W = gray_b.shape
    wh = np.array([W, H], np.float32)
    b_rot = np.ascontiguousarray(gray_b[::-1, ::-1])
    uv_b_rot = wh - uv_b_px
    f_ab_rot = dense_flow(gray_a, b_rot, uv_a_px, uv_b_rot)
    f_ba_rot = dense_flow(b_rot, gray_a, uv_b_rot, uv_a_px)
    v, u = np.mgrid[0:H, 0:W].astype(np.float32) + 0.5
    p = np.stack([u, v], -1)
    # a -> b: target in b = (W, H) - target in rotated b.
    flow_ab = (wh - (p + f_ab_rot)) - p
    # b -> a at b's pixel p: rotated-b pixel (W, H) - p, stored at the 180-deg-rotated grid index.
    flow_ba = f_ba_rot[::-1, ::-1] + (wh - p) - p
    return np.ascontiguousarray(flow_ab, np.float32), np.ascontiguousarray(flow_ba, np.float32)


def pair_flows(gray_a: np.ndarray, gray_b: np.ndarray, uv_a_px: np.ndarray, uv_b_px: np.ndarray,
               R_b_from_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flows a -> b and b -> a ((H, W, 2) each) seeded by the matches; against b turned by 180 deg
    when the relative rotation `R_b_from_a` turns the image plane by more than 135 deg."""
    if abs(np.degrees(np.arctan2(R_b_from_a[1, 0], R_b_from_a[0, 0]))) > 135.0:
        return _flow_rotated_180(gray_a, gray_b, uv_a_px, uv_b_px)
    return dense_flow(gray_a, gray_b, uv_a_px, uv_b_px), dense_flow(gray_b, gray_a, uv_b_px, uv_a_px)


def _why_no_focal(rels: Sequence, two_view: TwoViewConfig) -> str:
    """Why none of the pairs tried determined the focal: counts of the causes, most specific first.

    `rels` are the pairs' uncalibrated relative poses (None: OpenCV's estimator failed on the pair).
    """
    if not rels:
        return "no pair has enough matches to try"
    planar = sum(r is not None and (r.homography_ratio or 0.0) >= two_view.max_homography_ratio for r in rels)
    failed = sum(r is None or (not r.success and (r.homography_ratio or 0.0) < two_view.max_homography_ratio)
                 for r in rels)
    loose = len(rels) - planar - failed
    parts = []
    if planar:
        parts.append(f"in {planar} a homography explains at least {two_view.max_homography_ratio:.0%} of the "
                     "matches (a planar scene, or a camera rotating about its centre: no baseline)")
    if loose:
        parts.append(f"in {loose} the focal is too uncertain (e.g. an object-centric orbit)")
    if failed:
        parts.append(f"{failed} gave no relative pose")
    return f"of the {len(rels)} pair{'s' if len(rels) != 1 else ''} tried, " + "; ".join(parts)


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


class ClassicalPointmapModel:
    """SIFT + two-view geometry + dense flow + triangulation as a `PointmapModel`.

    Args:
        config: `ClassicalPairConfig`.
        K_align: optional known intrinsics per image, (N, 3, 3) at the alignment
            resolution (undistorted images); None estimates a shared focal per pair.
        seed: RANSAC seed (deterministic results).
    """

    def __init__(self, config: ClassicalPairConfig = ClassicalPairConfig(), *, K_align: np.ndarray | None = None,
                 seed: int = 0):
        self.config = config
        self.K_align = None if K_align is None else np.asarray(K_align, np.float64)
        self.focal_determined = True  # until `shared_focal` finds otherwise
        #: Why the pairs tried by `shared_focal` did not determine the focal (a short phrase, "" if they did).
        self.focal_undetermined_why = ""
        self.sift_fallback_used = False  # set by `predict_pairs`
        self.sparse_matches: list[tuple[int, int, np.ndarray]] = []  # set by `predict_pairs`
        self.seed = seed
        self.focal_px_used: float | None = None  # the shared focal of the last `predict_pairs` (alignment px)
        self._image_hw: tuple[int, int] = (0, 0)
        self._matched = None  # (key, features, matches, failures, fallback used) of the last `predict_pairs`
        self._predicted = None  # (key, predictions, failures, sparse matches, focal) of the last `predict_pairs`

    def refocused(self, focal_px: float, n_images: int) -> ClassicalPointmapModel:
        """A model for the same images and pairs whose relative poses and pointmaps use `focal_px`.

        The SIFT features and matches of the last `predict_pairs` are reused. `focal_determined` carries
        over, so that an alignment whose focal no pair determined still checks the bundle adjustment's
        uncertainty.

        Args:
            focal_px: shared focal length in alignment pixels (principal point at the image centre).
            n_images: number of images of the last `predict_pairs`.

        Raises:
            ValueError: this model has not predicted pairs yet, or for another number of images.
        """
        if self._matched is None or self._matched[0][0] != n_images:
            raise ValueError("refocused() needs a predict_pairs() call on the same images first")
        H, W = self._image_hw
        K = np.array([[focal_px, 0.0, W / 2.0], [0.0, focal_px, H / 2.0], [0.0, 0.0, 1.0]])
        out = ClassicalPointmapModel(self.config, K_align=np.repeat(K[None], n_images, axis=0), seed=self.seed)
        out._matched, out._image_hw = self._matched, self._image_hw
        out.focal_determined = self.focal_determined
        out.focal_undetermined_why = self.focal_undetermined_why
        return out

    @property
    def pointmap_size_px(self) -> int:
        return self.config.pointmap_size_px

    def predict_pairs(self, images: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]]
                      ) -> tuple[list[PairPrediction], list[PairFailure]]:
        """Predict every pair; failures come back with reasons instead of raising.

        Without known intrinsics, the focal is found in two passes (InstantSplat's
        focal averaging, done before the alignment): every pair's shared-focal
        relative pose, then the median of the *well-determined* pair focals
        (`RelativePoseResult.focal_well_determined`; object-centric rings are a
        critical configuration for two-view focal estimation) becomes one
        calibration for the calibrated relative pose of every pair.

        Args:
            images: N images (H, W, 3) float32 RGB at the alignment resolution.
            pairs: (i, j) index pairs.
        """
        cfg = self.config
        key = (len(images), tuple(pairs))
        if self._predicted is not None and self._predicted[0] == key:
            # A second start of the alignment on the same images and pairs (`AlignConfig.init_fallback`):
            # every step below is deterministic, so the pair stage is reused as it is.
            _, preds, fails, self.sparse_matches, self.focal_px_used = self._predicted
            return list(preds), list(fails)
        pool = ThreadPoolExecutor(max_workers=cfg.workers or os.cpu_count() or 1)
        try:
            preds, fails = self._predict_pairs(images, pairs, pool)
        finally:
            pool.shutdown()
        self._predicted = (key, list(preds), list(fails), self.sparse_matches, self.focal_px_used)
        return preds, fails

    def _predict_pairs(self, images, pairs, pool: ThreadPoolExecutor):
        # Threads: OpenCV and BLAS release the GIL; every task is independent and deterministic,
        # and results are collected in submission order.
        cfg = self.config
        key = (len(images), tuple(pairs))
        if self._matched is not None and self._matched[0] == key:  # `refocused`: same images and pairs
            _, feats, matches, fails, self.sift_fallback_used = self._matched
            fails = list(fails)
        else:
            feats, matches, fails = self._features_and_matches(images, pairs, pool, cfg.sift_contrast_threshold,
                                                               cfg.sift_blur_sigma_px)
            n_comp = len(components(len(images), list(matches)))
            self.sift_fallback_used = False
            if cfg.fallback_sift and n_comp > 1:
                alt = self._features_and_matches(images, pairs, pool, cfg.fallback_contrast_threshold,
                                                 cfg.fallback_blur_sigma_px)
                n_alt = len(components(len(images), list(alt[1])))
                _log.warning("SIFT match graph has %d components; COLMAP-like sensitive SIFT (contrast %.3g, "
                             "blur %.2g px) gives %d", n_comp, cfg.fallback_contrast_threshold,
                             cfg.fallback_blur_sigma_px, n_alt)
                if n_alt < n_comp or (n_alt == n_comp and len(alt[1]) > len(matches)):
                    feats, matches, fails = alt
                    self.sift_fallback_used = True
            self._matched = (key, feats, matches, list(fails), self.sift_fallback_used)
            self._image_hw = images[0].shape[:2]
        two_view = cfg.two_view
        if self.sift_fallback_used:
            two_view = replace(two_view, min_inliers=max(two_view.min_inliers, cfg.fallback_min_inliers),
                               refine=two_view.refine or cfg.fallback_refine)
        small = []
        for im in images:
            hw = pointmap_shape(im.shape[0], im.shape[1], cfg.pointmap_size_px)
            small.append(_gray_u8(_resize(im, hw)))
        K_align = self.K_align
        if K_align is None:
            f = self.shared_focal(images, feats, matches, pool)
            Ha, Wa = images[0].shape[:2]
            K = np.array([[f, 0, Wa / 2.0], [0, f, Ha / 2.0], [0, 0, 1]])
            K_align = np.repeat(K[None], len(images), axis=0)
        self.focal_px_used = float(np.median(K_align[:, 0, 0]))
        rels = {}
        def relative(item):
            (i, j), m = item
            u1, u2 = feats[i].uv_px[m[:, 0]], feats[j].uv_px[m[:, 1]]
            try:
                return estimate_relative_pose(u1, u2, K_align[i], K_align[j], config=two_view), u1, u2
            except cv2.error as exc:  # USAC asserts on some degenerate inputs (measured at 256 px)
                return f"OpenCV robust estimation failed: {str(exc).strip().splitlines()[-1][:200]}", u1, u2

        for ((i, j), _), (rel, u1, u2) in zip(matches.items(), pool.map(relative, matches.items()), strict=True):
            if isinstance(rel, str):
                fails.append(PairFailure(i, j, rel))
            elif rel.success:
                rels[(i, j)] = (rel, u1, u2)
            else:
                fails.append(PairFailure(i, j, f"relative pose: {rel.reason}"))
        self.sparse_matches = [(i, j, np.concatenate([u1[r.inlier_mask], u2[r.inlier_mask]], axis=1))
                               for (i, j), (r, u1, u2) in rels.items()]
        order = select_dense_pairs(len(images), {k: v[0].n_inliers for k, v in rels.items()}, cfg.dense_top_k)
        preds, done = [], set()

        def dense(ij):
            try:
                return self._dense(images, small, K_align, *ij, *rels[ij])
            except (_PairFailed, DegenerateGeometryError) as exc:
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
        return preds, sorted(fails, key=lambda f: (f.i, f.j))

    def _features_and_matches(self, images, pairs, pool: ThreadPoolExecutor, contrast: float, blur: float):
        """SIFT of every image and putative matches of every pair (fewer than `min_matches`: a failure)."""
        cfg = self.config
        def sift(im):
            f = extract_features(im, n_features=cfg.sift_features, blur_sigma_px=blur, contrast_threshold=contrast)
            f.root_t()  # RootSIFT once per image, here in parallel (not raced for by the matching threads)
            return f

        feats = list(progress(pool.map(sift, images), desc="SIFT", total=len(images)))
        matches: dict[tuple[int, int], np.ndarray] = {}
        fails: list[PairFailure] = []
        all_m = pool.map(lambda ij: match_features(feats[ij[0]], feats[ij[1]], ratio=cfg.ratio), pairs)
        for (i, j), m in zip(pairs, all_m, strict=True):
            if len(m) < cfg.min_matches:
                fails.append(PairFailure(i, j, f"only {len(m)} SIFT matches (need {cfg.min_matches})"))
            else:
                matches[(i, j)] = m
        return feats, matches, fails

    def shared_focal(self, images, feats, matches, pool: ThreadPoolExecutor | None = None) -> float:
        """Median of the well-determined pair focals (alignment pixels), or the prior."""
        Ha, Wa = images[0].shape[:2]
        best = sorted(matches.items(), key=lambda kv: -len(kv[1]))[:self.config.focal_pairs]

        def one(item):
            (i, j), m = item
            u1, u2 = feats[i].uv_px[m[:, 0]], feats[j].uv_px[m[:, 1]]
            try:
                return estimate_relative_pose_uncalibrated(u1, u2, (Wa, Ha), config=self.config.two_view,
                                                           seed=self.seed)
            except cv2.error:  # USAC assertion on a degenerate sample set: this pair gives no focal
                return None

        rels = list(progress((pool.map if pool else map)(one, best), desc="pair focals", total=len(best)))
        focals = [float(r.focal_px) for r in rels if r is not None and r.success and r.focal_well_determined]
        self.focal_determined = bool(focals)
        self.focal_undetermined_why = "" if focals else _why_no_focal(rels, self.config.two_view)
        if focals:
            f = float(np.median(focals))
            _log.info("shared focal %.1f px (median of %d well-determined pairs of %d)", f, len(focals), len(matches))
        else:
            f = self.config.focal_prior * max(Wa, Ha)
            _log.warning("no pair determines the focal length; using the prior %.2f * max(W, H) = %.1f px",
                         self.config.focal_prior, f)
        return f

    def _dense(self, images, small, K_align, i: int, j: int, rel, u1, u2) -> PairPrediction:
        # Everything below works on the pointmap grid.
        Hi, Wi = small[i].shape
        Hj, Wj = small[j].shape
        if Hi != Hj or Wi != Wj:
            raise _PairFailed("images of different sizes are not supported by the dense matcher")
        si, sj = Wi / images[i].shape[1], Wj / images[j].shape[1]
        Ki, Kj = K_align[i].copy(), K_align[j].copy()
        Ki[:2] *= si
        Kj[:2] *= sj
        inl = rel.inlier_mask
        a, b = u1[inl] * si, u2[inl] * sj
        R, t = rel.R, rel.t  # cam_j_from_cam_i, |t| = 1
        flow_ij, flow_ji = pair_flows(small[i], small[j], a, b, R)
        F = np.linalg.inv(Kj).T @ skew(t) @ R @ np.linalg.inv(Ki)
        cam_j_from_i = np.concatenate([R, t.reshape(3, 1)], axis=1)
        cam_i_from_j = np.concatenate([R.T, (-R.T @ t).reshape(3, 1)], axis=1)
        pts_i, conf_i = self._pointmap(flow_ij, flow_ji, Ki, Kj, F, cam_j_from_i)
        pts_j_in_j, conf_j = self._pointmap(flow_ji, flow_ij, Kj, Ki, F.T, cam_i_from_j)
        pts_j = pts_j_in_j @ R  # R^T (x_j - t)
        pts_j = pts_j - (R.T @ t)
        n_ok = int(np.count_nonzero(conf_i > 1) + np.count_nonzero(conf_j > 1))
        if n_ok < 0.02 * (conf_i.size + conf_j.size):
            raise _PairFailed(f"only {n_ok} dense pixels passed the consistency checks")
        return PairPrediction(i, j, pts_i.astype(np.float32), pts_j.astype(np.float32), conf_i.astype(np.float32),
                              conf_j.astype(np.float32), float(Ki[0, 0]), float(Kj[0, 0]),
                              matches_px=np.concatenate([u1[inl], u2[inl]], axis=1))

    def _pointmap(self, flow_ab, flow_ba, Ka, Kb, F_ab, cam_b_from_a) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) points of view a's pixels in frame a, (H, W) confidence."""
        cfg = self.config
        H, W = flow_ab.shape[:2]
        fb, inside, sampson, rays_a, rays_b = flow_checks(flow_ab, flow_ba, Ka, Kb, F_ab)
        # Triangulate only the pixels that pass the cheap checks: the others get confidence 1 and the
        # placeholder depth whatever their triangulation (rows are independent: same values).
        pre = np.flatnonzero(inside & (fb < cfg.fb_max_px) & (sampson < cfg.epipolar_max_px))
        tri = triangulate_two_view(rays_a[pre], rays_b[pre], cam_b_from_a, criteria=cfg.triangulation)
        ok_pre = tri.valid
        ok = np.zeros(len(rays_a), bool)
        ok[pre[ok_pre]] = True
        sel = pre[ok_pre]
        q = (np.exp(-0.5 * (fb[sel] / (0.5 * cfg.fb_max_px)) ** 2)
             * np.minimum(tri.angle_deg[ok_pre] / cfg.angle_ref_deg, 1.0)
             * np.exp(-0.5 * (sampson[sel] / (0.5 * cfg.epipolar_max_px)) ** 2))
        conf = np.ones(len(rays_a))
        conf[sel] = 1.0 + cfg.conf_max * q
        if len(sel):
            pts = np.empty((len(rays_a), 3))
            pts[sel] = tri.points[ok_pre]
            med = float(np.median(pts[sel, 2]))
            pts[~ok] = rays_a[~ok] / rays_a[~ok, 2:3] * med
        else:
            pts = rays_a / rays_a[:, 2:3]
        return pts.reshape(H, W, 3), conf.reshape(H, W)

    def _pointmap_reference(self, flow_ab, flow_ba, Ka, Kb, F_ab, cam_b_from_a) -> tuple[np.ndarray, np.ndarray]:
        """Slow, obvious `_pointmap` (triangulates every pixel, then masks): the tests' reference."""
        cfg = self.config
        H, W = flow_ab.shape[:2]
        fb, inside, sampson, rays_a, rays_b = flow_checks(flow_ab, flow_ba, Ka, Kb, F_ab)
        tri = triangulate_two_view(rays_a, rays_b, cam_b_from_a, criteria=cfg.triangulation)
        ok = inside & (fb < cfg.fb_max_px) & (sampson < cfg.epipolar_max_px) & tri.valid
        q = (np.exp(-0.5 * (fb / (0.5 * cfg.fb_max_px)) ** 2)
             * np.minimum(tri.angle_deg / cfg.angle_ref_deg, 1.0)
             * np.exp(-0.5 * (sampson / (0.5 * cfg.epipolar_max_px)) ** 2))
        conf = np.where(ok, 1.0 + cfg.conf_max * q, 1.0)
        pts = tri.points.copy()
        if np.any(ok):
            med = float(np.median(pts[ok, 2]))
            pts[~ok] = rays_a[~ok] / rays_a[~ok, 2:3] * med
        else:
            pts = rays_a / rays_a[:, 2:3]
        return pts.reshape(H, W, 3), conf.reshape(H, W)


def flow_checks(flow_ab, flow_ba, Ka, Kb, F_ab):
    """Per pixel of view a (row-major): forward-backward flow error, target inside view b, Sampson
    distance to F_ab, and the rays of the pixel and of its flow target (camera frames)."""
    H, W = flow_ab.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    ua = np.stack([u, v], -1).reshape(-1, 2)
    ub = ua + flow_ab.reshape(-1, 2)
    # Backward flow sampled at the forward target (bilinear; OpenCV centres at integers).
    back = cv2.remap(flow_ba, (ub[:, 0] - 0.5).astype(np.float32).reshape(H, W),
                     (ub[:, 1] - 0.5).astype(np.float32).reshape(H, W), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=(1e6, 1e6))
    d = flow_ab.reshape(-1, 2) + back.reshape(-1, 2)
    fb = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])  # = np.linalg.norm(d, axis=1), faster on 2-long rows
    inside = (ub[:, 0] > 0) & (ub[:, 0] < W) & (ub[:, 1] > 0) & (ub[:, 1] < H)
    sampson = sampson_distance(F_ab, ua, ub)
    rays_a = np.concatenate([ua, np.ones((len(ua), 1))], 1) @ np.linalg.inv(Ka).T
    rays_b = np.concatenate([ub, np.ones((len(ub), 1))], 1) @ np.linalg.inv(Kb).T
    return fb, inside, sampson, rays_a, rays_b


class _PairFailed(Exception):
    pass

