"""Pointmap geometry shared by the global alignment (`mvgeo.align.global_align`) and its two
initialisations (`init_from_spanning_tree` there, `mvgeo.align.pose_chain.init_from_pair_poses`):
pixel rays, confidence-weighted Procrustes, the initial values `AlignInit` and each pair's
similarity into the world. Conventions: docs/conventions.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mvgeo.align.pairs import PairPrediction
from mvgeo.common.errors import DegenerateGeometryError, InputError
from mvgeo.transforms import umeyama

__all__ = ["PNP_REFINE_POINTS", "AlignInit", "pair_similarities", "pixel_rays", "valid_pointmap_pixels",
           "weighted_umeyama"]


#: The LM refinement of an initial PnP pose on a pointmap uses at most this many pixels, evenly spread
#: (all 12k of a 128 x 96 pointmap took ~18 ms per view; 3000 ~4 ms; it only starts the alignment).
PNP_REFINE_POINTS = 3000


def weighted_umeyama(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Confidence-weighted Procrustes with scale: (s, R, t) with dst ~ s R src + t (mvgeo.transforms.umeyama).

    Raises:
        DegenerateGeometryError: fewer than 3 weighted points, or a degenerate configuration.
    """
    if np.count_nonzero(w > 0) < 3:
        raise DegenerateGeometryError("Procrustes needs at least 3 points with positive confidence")
    sim = umeyama(src, dst, weights=w, with_scale=True)
    if not sim.scale > 0:
        raise DegenerateGeometryError("Procrustes gave a non-positive scale (all target points coincide)")
    return float(sim.scale), sim.R, sim.t


def pixel_rays(H: int, W: int, focal_px: float) -> np.ndarray:
    """(H, W, 3) rays (x/z, y/z, 1) of the pixel centres, principal point at (W/2, H/2)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    return np.stack([(u - W / 2.0) / focal_px, (v - H / 2.0) / focal_px, np.ones_like(u)], axis=-1)


@dataclass
class AlignInit:
    """Initial values (numpy float64) for the optimisation.

    `pair_sim`, each pair's similarity into the world, is None where the initialisation leaves it to
    `global_align`, which fits it (`pair_similarities`) on the pixels its objective samples.
    """

    cam_from_world: np.ndarray  # (N, 3, 4)
    focal_px: np.ndarray  # (N,)
    depth: list[np.ndarray]  # (H_n, W_n)
    pair_sim: list[tuple[float, np.ndarray, np.ndarray]] | None = None  # pair frame -> world


def valid_pointmap_pixels(C: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(H, W) mask of the pixels a pointmap can be trusted at: confidence above 1 and a finite point."""
    return (C > 1.0) & np.all(np.isfinite(P), axis=-1)


def pair_similarities(preds: Sequence[PairPrediction], sizes_hw: Sequence[tuple[int, int]], cam_from_world: np.ndarray,
                      depth: Sequence[np.ndarray], focal_px: np.ndarray, *, pixel_stride: int = 1
                      ) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Each pair's similarity (s, R, t): pair frame -> world, by weighted Procrustes against the posed depth maps.

    Each view's posed depth map (world points, (H, W, 3)) is computed once and shared by its pairs.
    `pixel_stride`: only the pixels on every `pixel_stride`-th row and column (offset `pixel_stride // 2`,
    the global alignment's samples) enter the fit; a pair whose samples hold too few confident points for
    it is fitted on all its pixels.

    Raises:
        DegenerateGeometryError: a pair's fit is degenerate on all its pixels.
    """
    if pixel_stride < 1:
        raise InputError(f"pixel_stride must be >= 1, got {pixel_stride}")
    posed: dict[tuple[int, int], np.ndarray] = {}

    def world_points(v: int, k: int) -> np.ndarray:
        if (v, k) not in posed:
            H, W = sizes_hw[v]
            R, t = cam_from_world[v][:, :3], cam_from_world[v][:, 3]
            rays = pixel_rays(H, W, float(focal_px[v]))[k // 2::k, k // 2::k]
            posed[v, k] = (rays * depth[v][k // 2::k, k // 2::k, None] - t) @ R  # R^T (x - t)
        return posed[v, k]

    def fit(p: PairPrediction, k: int) -> tuple[float, np.ndarray, np.ndarray]:
        src, dst, w = [], [], []
        for v, P, C in ((p.i, p.pts_i, p.conf_i), (p.j, p.pts_j, p.conf_j)):
            P, C = P[k // 2::k, k // 2::k], C[k // 2::k, k // 2::k]
            ok = valid_pointmap_pixels(C, P)
            src.append(P[ok].astype(np.float64))
            dst.append(world_points(v, k)[ok])
            w.append(np.log(C[ok]))
        return weighted_umeyama(np.concatenate(src), np.concatenate(dst), np.concatenate(w))

    pair_sim = []
    for p in preds:
        try:
            pair_sim.append(fit(p, pixel_stride))
        except DegenerateGeometryError:
            if pixel_stride == 1:
                raise
            pair_sim.append(fit(p, 1))
    return pair_sim
