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
from dataclasses import dataclass
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


@runtime_checkable
class PointmapModel(Protocol):
    """Anything that turns image pairs into `PairPrediction`s.

    `predict_pairs(images, pairs)` receives all N images, (H, W, 3) float32 RGB
    in [0, 1] at the alignment resolution (long side <= `--max-size`), and the
    (i, j) pairs of the pair graph. It returns the predictions, with pointmaps
    on a grid whose long side is `pointmap_size_px` (see
    `mvgeo.align.classical_pairs.pointmap_shape`), and a `PairFailure` with a
    human-readable reason for every pair it could not relate (reported in
    align.json, never raised). Batching over pairs lets a model reuse per-image
    work (features, encoder outputs).

    A learned DUSt3R/MASt3R wrapper fits here: run the network on each (i, j),
    return its `pts3d` / `pts3d_in_other_view` / `conf` outputs as
    `pts_i` / `pts_j` / `conf_i`, `conf_j` (its confidences are already >= 1),
    and a focal estimated from `pts_i` with `focal_from_pointmap`; pass it as
    `mvgeo.align.align_images(..., model=MyModel())`.
    """

    @property
    def pointmap_size_px(self) -> int: ...

    def predict_pairs(self, images: Sequence[np.ndarray], pairs: Sequence[tuple[int, int]]
                      ) -> tuple[list[PairPrediction], list[PairFailure]]: ...


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
