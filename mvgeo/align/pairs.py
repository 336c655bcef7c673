"""Pairwise pose-free pointmaps in DUSt3R's format, and the model protocol.

A `PairPrediction` is what DUSt3R/MASt3R regress for an image pair (i, j)
with unknown intrinsics and poses: both views' pointmaps expressed in camera
i's frame (OpenCV axes, arbitrary scale), a per-pixel confidence >= 1 for
each, and a focal estimate. Any `PointmapModel` (the classical estimator in
`mvgeo.align.classical_pairs`, or a user's learned model) can feed the
global alignment in `mvgeo.align.global_align`.

Pixel grid: pixel `(row, col)` of a pointmap has centre `(col + 0.5, row + 0.5)`
and the principal point is assumed at the image centre `(W / 2, H / 2)`
(docs/conventions.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import numpy as np

from mvgeo.common.errors import ShapeError, check_shape


@dataclass
class PairPrediction:
    """DUSt3R-style prediction for the ordered pair (i, j).

    Attributes:
        i: index of the first view (the reference frame of both pointmaps).
        j: index of the second view.
        pts_i: (H_i, W_i, 3) float32, view i's pixels as 3D points in camera i's frame.
        pts_j: (H_j, W_j, 3) float32, view j's pixels as 3D points in camera i's frame.
        conf_i: (H_i, W_i) float32 confidence >= 1 (1 means "no information":
            the global alignment weights residuals by log(conf)).
        conf_j: (H_j, W_j) float32 confidence >= 1.
        focal_i_px: focal length of view i in pixels of the pointmap grid.
        focal_j_px: focal of view j in pixels of its pointmap grid, or None when
            the model does not estimate it (DUSt3R does not; the classical
            estimator assumes one shared focal per pair and sets both).
        matches_px: optional (M, 4) sparse inlier matches `(u_i, v_i, u_j, v_j)`
            in pixels of the images the model was given (our convention); the
            optional bundle adjustment uses them.
    """

    i: int
    j: int
    pts_i: np.ndarray
    pts_j: np.ndarray
    conf_i: np.ndarray
    conf_j: np.ndarray
    focal_i_px: float
    focal_j_px: float | None = None
    matches_px: np.ndarray | None = None

    def __post_init__(self) -> None:
        check_shape(self.pts_i, ["H", "W", 3], "pts_i")
        check_shape(self.pts_j, ["H", "W", 3], "pts_j")
        if self.conf_i.shape != self.pts_i.shape[:2]:
            raise ShapeError(f"conf_i: expected {self.pts_i.shape[:2]}, got {self.conf_i.shape}")
        if self.conf_j.shape != self.pts_j.shape[:2]:
            raise ShapeError(f"conf_j: expected {self.pts_j.shape[:2]}, got {self.conf_j.shape}")
        if self.i == self.j:
            raise ShapeError(f"a pair needs two different views, got i == j == {self.i}")

    @property
    def score(self) -> float:
        """Pair confidence used for the spanning tree: mean(conf_i) * mean(conf_j) (as DUSt3R)."""
        return float(np.mean(self.conf_i) * np.mean(self.conf_j))


@dataclass
class PairFailure:
    """A pair the model could not predict, with the reason (reported in align.json)."""

    i: int
    j: int
    reason: str


@dataclass(frozen=True)
class PairGeometry:
    """A verified pair's two-view geometry: its inlier matches and, where the model has it, its relative pose.

    Attributes:
        i, j: view indices (i < j for the classical model).
        matches_px: (M, 4) inlier matches `(u_i, v_i, u_j, v_j)` in pixels of the images the model was given.
        cam_j_from_cam_i: (3, 4) relative pose with a unit translation, or None when the model has none.
    """

    i: int
    j: int
    matches_px: np.ndarray
    cam_j_from_cam_i: np.ndarray | None = None

    def __post_init__(self) -> None:
        check_shape(self.matches_px, ["M", 4], "matches_px")
        if self.cam_j_from_cam_i is not None:
            check_shape(self.cam_j_from_cam_i, [3, 4], "cam_j_from_cam_i")


class Keypoints(Protocol):
    """One view's keypoints as the alignment's later stages read them: `uv_px` (K, 2) pixels (our convention)
    and `root()` (K, D) unit-norm descriptors (RootSIFT for `mvgeo.align.features.ImageFeatures`)."""

    uv_px: np.ndarray

    def root(self) -> np.ndarray: ...


@dataclass(frozen=True)
class PairSet:
    """Everything a `PointmapModel` knows about the image pairs (the pair stage's result).

    Attributes:
        predictions: dense pointmaps (the global alignment's input); the classical model computes them
            for a subset of the verified pairs (`ClassicalPairConfig.dense_top_k`).
        failures: every pair the model could not relate, with the reason.
        geometries: every verified pair (a superset of the predictions' pairs): the bundle adjustment,
            the loop check and the rotation averaging use all of them. Empty when the model has no
            sparse matches (then the bundle adjustment is skipped).
        focal_determined: whether the pairs determine the focal length. No default: a model that cannot
            tell says False, and the alignment then checks the bundle adjustment's focal uncertainty
            (`AlignConfig.max_focal_log_std`).
        focal_px: the one focal length (alignment pixels) the pair geometry assumed, or None when each pair
            estimated its own (DUSt3R) or the intrinsics were given per view.
        focal_undetermined_why: why the pairs do not determine the focal (a phrase for the error message).
        focal_prior_px: the focal length prior (alignment pixels, e.g. the photos' EXIF focal) the pairs
            started from, or None. A bundle adjustment that keeps the focal within
            `AlignConfig.refocus_min_change` of it counts as determining the focal (`mvgeo.align.solve`).
        sensitive_features: the model re-detected features with a more sensitive detector to connect the
            pair graph (`ClassicalPairConfig.fallback_sift`).
        features: per view, the keypoints and descriptors the matches came from (`Keypoints`, e.g.
            `mvgeo.align.features.ImageFeatures`; alignment pixels), or None (a model without sparse
            features). `mvgeo.align.locate` matches them again to locate a view the verdict cuts off.
    """

    predictions: list[PairPrediction]
    failures: list[PairFailure]
    geometries: list[PairGeometry]
    focal_determined: bool
    focal_px: float | None = None
    focal_undetermined_why: str = ""
    sensitive_features: bool = False
    focal_prior_px: float | None = None
    features: tuple[Keypoints, ...] | None = None

    @property
    def matches(self) -> list[tuple[int, int, np.ndarray]]:
        """`(i, j, (M, 4) matches_px)` of every verified pair (the bundle adjustment's input format)."""
        return [(g.i, g.j, g.matches_px) for g in self.geometries]

    def without_pairs(self, gone: set[tuple[int, int]]) -> PairSet:
        """The same set with the pairs `gone` ((i, j) as stored) removed from predictions and geometries."""
        return replace(self, predictions=[p for p in self.predictions if (p.i, p.j) not in gone],
                       geometries=[g for g in self.geometries if (g.i, g.j) not in gone])

    def restricted(self, keep: Sequence[int]) -> PairSet:
        """Only the views `keep`, renumbered in that order (pairs with another view are dropped)."""
        new = {v: k for k, v in enumerate(keep)}
        return replace(
            self,
            predictions=[replace(p, i=new[p.i], j=new[p.j]) for p in self.predictions if p.i in new and p.j in new],
            failures=[replace(f, i=new[f.i], j=new[f.j]) for f in self.failures if f.i in new and f.j in new],
            geometries=[replace(g, i=new[g.i], j=new[g.j]) for g in self.geometries if g.i in new and g.j in new],
            features=None if self.features is None else tuple(self.features[v] for v in keep))


@runtime_checkable
class PointmapModel(Protocol):
    """Anything that turns image pairs into a `PairSet`.

    `predict_pairs(images, pairs)` receives all N images, (H, W, 3) float32 RGB
    in [0, 1] at the alignment resolution (long side <= `--max-size`), and the
    (i, j) pairs of the pair graph. It returns a `PairSet`: pointmaps on a grid
    whose long side is `pointmap_size_px` (see
    `mvgeo.align.classical_pairs.pointmap_shape`), a `PairFailure` with a
    human-readable reason for every pair it could not relate (reported in
    align.json, never raised), the verified pairs' matches if it has any, and
    whether the pairs determine the focal length. Batching over pairs lets a
    model reuse per-image work (features, encoder outputs).

    A learned DUSt3R/MASt3R wrapper fits here: run the network on each (i, j),
    return its `pts3d` / `pts3d_in_other_view` / `conf` outputs as
    `pts_i` / `pts_j` / `conf_i`, `conf_j` (its confidences are already >= 1),
    and a focal estimated from `pts_i` with `focal_from_pointmap`; pass it as
    `mvgeo.align.align_images(..., model=MyModel())`.
    """

    @property
    def pointmap_size_px(self) -> int: ...

    def predict_pairs(self, images: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]]) -> PairSet: ...


@runtime_checkable
class RefocusableModel(PointmapModel, Protocol):
    """A `PointmapModel` that can recompute its pair geometry at another shared focal length from the same
    features and matches (the classical model): the alignment's focal re-estimation needs it
    (`AlignConfig.refocus_min_change`)."""

    def refocus(self, images: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]], focal_px: float) -> PairSet: ...


def focal_from_pointmap(pts: np.ndarray, conf: np.ndarray | None = None) -> float:
    """Least-squares focal of a pointmap in its own camera frame, principal point at the centre.

    Minimises sum_w ||(u - c) - f * (X, Y) / Z||^2 over f in closed form.

    Args:
        pts: (H, W, 3) points in the camera's own frame.
        conf: (H, W) optional weights (confidence).

    Returns:
        focal in pixels; nan when no point has positive depth.
    """
    check_shape(pts, ["H", "W", 3], "pts")
    H, W = pts.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    du, dv = u - W / 2.0, v - H / 2.0
    z = pts[..., 2].astype(np.float64)
    ok = z > 1e-9
    if not np.any(ok):
        return float("nan")
    w = np.ones_like(z) if conf is None else np.asarray(conf, np.float64)
    x = pts[..., 0][ok] / z[ok]
    y = pts[..., 1][ok] / z[ok]
    w = w[ok]
    num = np.sum(w * (du[ok] * x + dv[ok] * y))
    den = np.sum(w * (x * x + y * y))
    return float(num / den) if den > 0 else float("nan")
