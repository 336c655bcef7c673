"""Smooth filling of the holes that dense stereo leaves in textureless surfaces.

Flow stereo finds no correspondences on a uniform surface (a white table, a plain wall), so its depth
map has a hole there, the cloud has no points, and a splat initialised from the cloud renders the
background instead (measured on DTU scan24: the table around the model, after denoising, which
removes the last texture). On such a surface the depth matters little to the colour of a nearby view,
but the points must exist. Each view's holes are therefore filled with the harmonic (membrane)
interpolation of the *inverse* depth from the hole's border: the solution of Laplace's equation on the
hole pixels, the measured pixels around them fixed, zero normal derivative at the image border. Inverse
depth is affine in the pixel coordinates on a plane, and affine functions are harmonic, so a planar
surface seen all around its hole is continued exactly. The filled pixels get the low confidence
`fill_conf`.

Only *wide* holes are filled: the parts of a hole that a disc of diameter `min_width` (a fraction of
the long side) fits in (a morphological opening of the hole mask). Narrow holes are stereo failures
around depth edges, occlusions or in noise on textured surfaces; the Gaussians of the points around
them cover them, and an interpolated depth there is often wrong. On 6 noisy llff_like views (256x192,
dev probe) the points filled into every hole had a median depth error of 11 % (the stereo's: 2.4 %); in
the 12-view llff_like evaluation, filling every hole cost the splat of the noisy photos 0.27 dB held
out, and filling the wide ones 0.16 dB.
On DTU scan24 the table's holes keep most of their fill (13-67 % of each view's pixels, against 19-73 %
without the limit), and the denoised photos' splat gains 4.2 dB held out (docs/bench/pipeline.md).

The filled points are checked downstream like any other (co-visibility, multi-view consistency and
free-space pruning, `mvgeo.align.scene.covisibility_keep`): a filled point that another view sees
through, or that the views which see its direction do not confirm (filled depth included), is dropped
there. A filled pixel is no evidence about other views' measured points: it neither confirms them nor
carves them away.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.linalg import spsolve

from mvgeo.common.deps import cv2
from mvgeo.common.threads import pool_threads

__all__ = ["HoleFillConfig", "fill_depth_holes", "harmonic_fill", "wide_holes"]


@dataclass(frozen=True)
class HoleFillConfig:
    """Options of `fill_depth_holes`.

    Attributes:
        enabled: run it.
        min_valid_fraction: a view with less depth than this is left as it is (too little to
            interpolate from).
        min_width: holes narrower than this fraction of the depth map's long side are left empty
            (0.05: 13 px at 256 px).
        fill_conf: confidence of a filled pixel: just above `AlignConfig.min_conf` (2), so the points
            are kept, and below most measured ones, so the co-visibility pruning prefers measured depth.
    """

    enabled: bool = True
    min_valid_fraction: float = 0.05
    min_width: float = 0.05
    fill_conf: float = 2.5


def harmonic_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(H, W) `values` with the unknown pixels replaced by the harmonic interpolation of the known ones.

    Solves the 5-point discrete Laplace equation on the unknown pixels (a sparse LU solve; ~0.2 s for
    50k unknowns): each unknown pixel equals the mean of its 4-neighbours inside the image (so the image
    border is a zero-normal-derivative boundary), the known neighbours fixed. With at least one known
    pixel, every 4-connected region of unknown pixels has a known neighbour (a maximal region with none
    would be the whole image), so the system is positive definite. `known` must not be all False.
    """
    H, W = values.shape
    unk = ~np.asarray(known, bool)
    out = np.array(values, np.float64)
    n = int(unk.sum())
    if n == 0:
        return out
    if n == unk.size:
        raise ValueError("harmonic_fill needs at least one known pixel")
    idx = np.full((H, W), -1, np.int64)
    idx[unk] = np.arange(n)
    r, c = np.nonzero(unk)
    me = idx[r, c]
    deg = np.zeros(n)
    b = np.zeros(n)
    rows, cols = [me], [me]
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        rr, cc = r + dr, c + dc
        inside = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
        deg += inside
        rr, cc, mi = rr[inside], cc[inside], me[inside]
        nb_unknown = unk[rr, cc]
        rows.append(mi[nb_unknown])
        cols.append(idx[rr[nb_unknown], cc[nb_unknown]])
        b += np.bincount(mi[~nb_unknown], out[rr[~nb_unknown], cc[~nb_unknown]], minlength=n)
    vals = [deg] + [-np.ones(len(x)) for x in rows[1:]]
    A = csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    out[unk] = spsolve(A, b)
    return out


def wide_holes(hole: np.ndarray, min_width: float) -> np.ndarray:
    """(H, W) bool: the pixels of `hole` that some disc of diameter `min_width` x max(H, W) inside
    `hole` covers: the morphological opening of the mask by that disc. Outside the image counts as
    hole, so a hole along the border is judged by its width inside the image."""
    hole = np.asarray(hole, bool)
    r = int(round(0.5 * min_width * max(hole.shape)))
    if r <= 0 or not hole.any():
        return hole.copy()
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    # OpenCV's erosion pads with the maximum (outside = hole), its dilation with the minimum.
    return cv2.morphologyEx(hole.astype(np.uint8), cv2.MORPH_OPEN, disc).astype(bool)


def fill_depth_holes(depth: Sequence[np.ndarray], conf: Sequence[np.ndarray],
                     config: HoleFillConfig = HoleFillConfig(), *, workers: int | None = None
                     ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Fill the wide holes of every view's depth with the harmonic interpolation of the inverse depth.

    Args:
        depth: N (H, W) z-depth maps, NaN (or <= 0) where there is no depth.
        conf: N (H, W) confidences.
        config: options.
        workers: threads over the views (default: the caller's, `mvgeo.common.threads.pool_threads`; SciPy's
            sparse LU solve releases the GIL, measured 1.5x faster on two cores for DTU scan24's 12 views); the
            results do not depend on it.

    Returns:
        depth, conf (float64 copies with the holes filled) and N (H, W) bool masks of the filled pixels.
    """

    def one(D: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        D = np.array(D, np.float64)
        C = np.array(C, np.float64)
        valid = np.isfinite(D) & (D > 0)
        mask = np.zeros(D.shape, bool)
        if config.enabled and not valid.all() and valid.mean() >= config.min_valid_fraction:
            wide = wide_holes(~valid, config.min_width)
            if wide.any():
                # Solve only on the 4-connected hole regions that contain wide pixels: the others are
                # separate blocks of the Laplace system (no 4-neighbour in common) and would be discarded.
                _, label = cv2.connectedComponents((~valid).astype(np.uint8), connectivity=4)
                region = np.isin(label, np.unique(label[wide]))
                inv = np.where(valid, 1.0 / np.where(valid, D, 1.0), 0.0)
                inv = harmonic_fill(inv, ~region)
                # A harmonic function stays within its boundary values (maximum principle): positive here.
                mask = wide & np.isfinite(inv) & (inv > 0)
                D[mask] = 1.0 / inv[mask]
                C[mask] = config.fill_conf
        return D, C, mask

    if len(depth) != len(conf):
        raise ValueError(f"{len(depth)} depth maps but {len(conf)} confidence maps")
    n_workers = pool_threads(workers, len(depth))
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        out = list(pool.map(one, depth, conf))
    return [o[0] for o in out], [o[1] for o in out], [o[2] for o in out]
