"""Dense depth maps from the final cameras: two-view flow stereo per pair, fused per view.

The pairwise pointmaps are triangulated with each pair's *own* relative pose, at the coarse pointmap
resolution; the global alignment can only average their errors (6-40 % relative depth per pair on the
noisy llff_like images, against 2 % for the bundle-adjusted feature tracks). Once the cameras are
final, the same dense correspondences (edge-aware densified matches refined by DIS optical flow, both
ways) are computed again at the alignment resolution and triangulated with the *global* cameras, as a
multi-view stereo with calibrated cameras would:

1. per pair (a, b): flows a -> b and b -> a, seeded by the pair's inlier matches; a pixel is used when
   the forward-backward error is below `fb_max_px`, its match lies inside b, and the match is within
   `epipolar_max_px` (Sampson) of the epipolar line of the *final* cameras;
2. each used pixel is triangulated (mid-point of the two rays) and must pass `triangulation`'s
   angle / reprojection criteria;
3. per view, each pixel's candidate depths from all its pairs are fused: the median, kept when at least
   half of the candidates agree with it within `agree_rel_tol`; the confidence is that of the best
   agreeing candidate (forward-backward error, Sampson distance and triangulation angle, as the
   classical pointmaps' confidence).

Pixels no pair triangulates get depth NaN and confidence 1 (no information).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from mvgeo.align.dense_pairs import flow_checks, pair_flows
from mvgeo.common.deps import cv2
from mvgeo.common.errors import DegenerateGeometryError, ShapeError
from mvgeo.common.progress import progress_bar
from mvgeo.common.threads import pool_threads
from mvgeo.transforms import skew
from mvgeo.triangulate import TriangulationCriteria, triangulate_two_view

__all__ = ["DenseStereoConfig", "StereoDepths", "fuse_depth_candidates", "fuse_depth_candidates_reference",
           "pair_depths", "stereo_depths"]


@dataclass(frozen=True)
class DenseStereoConfig:
    """Options of the dense stereo with the final cameras.

    Attributes:
        enabled: run it (`mvgeo align --no-dense-stereo` turns it off: the cloud then comes from the
            global alignment's depth maps, rescaled onto the bundle-adjusted tracks).
        size_px: long side of the stereo images (at most the alignment resolution; 0: that resolution).
            256 px gives 12 views ~0.5 M candidate points for the default 200k-point budget; at 504 px
            the stage took 4x the time (llff_like, 12 views: 14 s, more than the rest of `mvgeo align`).
        fb_max_px: forward-backward flow limit, pixels at the stereo resolution.
        epipolar_max_px: Sampson distance limit under the final cameras, pixels.
        agree_rel_tol: candidates within this relative depth of a pixel's median agree with it.
        angle_ref_deg: triangulation angle at which the angle term of the confidence saturates.
        conf_max: confidence of a perfect pixel is 1 + conf_max.
        triangulation: validity criteria of each two-view triangulation.
        workers: threads over pairs (0: the caller's, `mvgeo.common.threads.pool_threads`; OpenCV and numpy
            release the GIL).
        min_coverage: `mvgeo.align` keeps the global alignment's depth map for a view whose fused
            stereo depth covers less than this fraction of its pixels.
    """

    enabled: bool = True
    size_px: int = 256
    fb_max_px: float = 1.0
    epipolar_max_px: float = 1.0
    agree_rel_tol: float = 0.02
    angle_ref_deg: float = 5.0
    conf_max: float = 10.0
    triangulation: TriangulationCriteria = field(
        default_factory=lambda: TriangulationCriteria(min_angle_deg=1.0, max_angular_error_deg=1.0))
    workers: int = 0
    min_coverage: float = 0.05


@dataclass
class StereoDepths:
    """Fused per-view depth maps on the stereo grid.

    Attributes:
        depth: N (H, W) z-depth, NaN where no pair triangulated the pixel.
        conf: N (H, W) confidence >= 1 (1: no information).
        K: (N, 3, 3) intrinsics of the stereo grid (our pixel convention).
        n_candidates: N (H, W) int, how many pairs triangulated each pixel.
    """

    depth: list[np.ndarray]
    conf: list[np.ndarray]
    K: np.ndarray
    n_candidates: list[np.ndarray]


def _relative(cam_from_world: np.ndarray, a: int, b: int) -> np.ndarray:
    """(3, 4) cam_b_from_cam_a."""
    Ra, ta = cam_from_world[a][:, :3], cam_from_world[a][:, 3]
    Rb, tb = cam_from_world[b][:, :3], cam_from_world[b][:, 3]
    R = Rb @ Ra.T
    return np.concatenate([R, (tb - R @ ta)[:, None]], axis=1)


def pair_depths(gray_a: np.ndarray, gray_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                cam_b_from_a: np.ndarray, uv_a_px: np.ndarray, uv_b_px: np.ndarray,
                config: DenseStereoConfig = DenseStereoConfig()) -> tuple[np.ndarray, ...]:
    """Depths of both views' pixels from one pair with known cameras.

    Args:
        gray_a, gray_b: (H, W) uint8 images.
        K_a, K_b: (3, 3) intrinsics at this resolution.
        cam_b_from_a: (3, 4) relative pose.
        uv_a_px, uv_b_px: (M, 2) matches seeding the flow (our pixel convention).

    Returns:
        depth_a, q_a, depth_b, q_b: (H, W) each; depth NaN where the pixel failed a check, q in (0, 1]
        the pixel's quality (0 where it failed).
    """
    if gray_a.shape != gray_b.shape:
        raise ShapeError(f"stereo pair of different sizes: {gray_a.shape} and {gray_b.shape}")
    R, t = cam_b_from_a[:, :3], cam_b_from_a[:, 3]
    flow_ab, flow_ba = pair_flows(gray_a, gray_b, uv_a_px, uv_b_px, R)
    F_ab = np.linalg.inv(K_b).T @ skew(t) @ R @ np.linalg.inv(K_a)
    cam_a_from_b = np.concatenate([R.T, (-R.T @ t)[:, None]], axis=1)
    d_a, q_a = _one_way(flow_ab, flow_ba, K_a, K_b, F_ab, cam_b_from_a, config)
    d_b, q_b = _one_way(flow_ba, flow_ab, K_b, K_a, F_ab.T, cam_a_from_b, config)
    return d_a, q_a, d_b, q_b


def _one_way(flow_ab, flow_ba, K_a, K_b, F_ab, cam_b_from_a, config: DenseStereoConfig):
    H, W = flow_ab.shape[:2]
    fb, inside, sampson, rays_a, rays_b = flow_checks(flow_ab, flow_ba, K_a, K_b, F_ab)
    pre = np.flatnonzero(inside & (fb < config.fb_max_px) & (sampson < config.epipolar_max_px))
    depth, q = np.full(H * W, np.nan), np.zeros(H * W)
    if len(pre):
        try:
            tri = triangulate_two_view(rays_a[pre], rays_b[pre], cam_b_from_a, criteria=config.triangulation)
        except DegenerateGeometryError:  # the two cameras coincide (a pure rotation): no depth from this pair
            return depth.reshape(H, W), q.reshape(H, W)
        sel = pre[tri.valid]
        depth[sel] = tri.points[tri.valid, 2]
        q[sel] = (np.exp(-0.5 * (fb[sel] / (0.5 * config.fb_max_px)) ** 2)
                  * np.minimum(tri.angle_deg[tri.valid] / config.angle_ref_deg, 1.0)
                  * np.exp(-0.5 * (sampson[sel] / (0.5 * config.epipolar_max_px)) ** 2))
    return depth.reshape(H, W), q.reshape(H, W)


def fuse_depth_candidates(depth: np.ndarray, quality: np.ndarray, *, agree_rel_tol: float,
                          conf_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Fuse per-pixel candidate depths (vectorised; `fuse_depth_candidates_reference` is the loop).

    Args:
        depth: (C, H, W) candidates, NaN where a pair gave none.
        quality: (C, H, W) in [0, 1].

    Returns:
        depth (H, W): the candidates' median where at least half of them agree with it within
        `agree_rel_tol` (relative), else NaN; conf (H, W): 1 + conf_max x the best agreeing quality
        (1 where NaN).
    """
    valid = np.isfinite(depth)
    n_valid = valid.sum(axis=0)
    has = n_valid > 0
    med = np.full(depth.shape[1:], np.nan)
    if len(depth):
        # np.nanmedian(depth[:, has], axis=0) at half the cost: NaNs sort last, and the median is the mean
        # of the two middle valid candidates (the same one twice for an odd count), as numpy computes it.
        srt = np.sort(depth[:, has], axis=0)
        k = n_valid[has]
        lo = np.take_along_axis(srt, ((k - 1) // 2)[None], axis=0)[0]
        hi = np.take_along_axis(srt, (k // 2)[None], axis=0)[0]
        med[has] = (lo + hi) / 2.0
    with np.errstate(invalid="ignore"):
        agree = valid & (np.abs(depth - med[None]) <= agree_rel_tol * med[None])
    n_agree = agree.sum(axis=0)
    ok = has & (2 * n_agree >= n_valid)
    best = np.where(agree, quality, 0.0).max(axis=0) if len(depth) else np.zeros(depth.shape[1:])
    fused = np.where(ok, med, np.nan)
    conf = np.where(ok, 1.0 + conf_max * best, 1.0)
    return fused, conf


def fuse_depth_candidates_reference(depth: np.ndarray, quality: np.ndarray, *, agree_rel_tol: float,
                                    conf_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-by-pixel `fuse_depth_candidates` (the tests' reference)."""
    _, H, W = depth.shape
    fused, conf = np.full((H, W), np.nan), np.ones((H, W))
    for r in range(H):
        for c in range(W):
            cand = [(d, q) for d, q in zip(depth[:, r, c], quality[:, r, c], strict=True) if np.isfinite(d)]
            if not cand:
                continue
            med = float(np.median([d for d, _ in cand]))
            agreeing = [q for d, q in cand if abs(d - med) <= agree_rel_tol * med]
            if 2 * len(agreeing) >= len(cand):
                fused[r, c] = med
                conf[r, c] = 1.0 + conf_max * max(agreeing)
    return fused, conf


def stereo_depths(images: Sequence[np.ndarray], K: np.ndarray, cam_from_world: np.ndarray,
                  pairs: Sequence[tuple[int, int]], matches: dict[tuple[int, int], np.ndarray],
                  config: DenseStereoConfig = DenseStereoConfig()) -> StereoDepths:
    """Fused depth maps of every view from its pairs, with the cameras fixed.

    Args:
        images: N (H, W, 3) float RGB in [0, 1] at the resolution of `K` and of the matches.
        K: (N, 3, 3) intrinsics (our pixel convention). cam_from_world: (N, 3, 4).
        pairs: (i, j) pairs to match (each view should be in at least one).
        matches: (i, j) -> (M, 4) inlier matches (u_i, v_i, u_j, v_j) in pixels of `images`.
        config: `DenseStereoConfig`; `size_px` > 0 resamples the images (and K, matches) first.

    Returns:
        `StereoDepths` on the (possibly resampled) grid.
    """
    n = len(images)
    H0, W0 = images[0].shape[:2]
    s = 1.0 if config.size_px <= 0 else min(1.0, config.size_px / max(H0, W0))
    H, W = max(1, round(H0 * s)), max(1, round(W0 * s))
    sx, sy = W / W0, H / H0
    K = np.array(K, float)
    K[:, 0] *= sx
    K[:, 1] *= sy
    gray = []
    for im in images:
        g = cv2.cvtColor(np.ascontiguousarray(im, dtype=np.float32), cv2.COLOR_RGB2GRAY)
        if (H, W) != (H0, W0):
            g = cv2.resize(g, (W, H), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
        gray.append(np.clip(np.rint(g * 255.0), 0, 255).astype(np.uint8))
    cand_d = [[] for _ in range(n)]
    cand_q = [[] for _ in range(n)]
    scale = np.array([sx, sy, sx, sy])

    def one(ij):
        i, j = ij
        m = matches.get((i, j))
        uv = np.zeros((0, 4)) if m is None else np.asarray(m, float) * scale
        return pair_depths(gray[i], gray[j], K[i], K[j], _relative(cam_from_world, i, j), uv[:, :2], uv[:, 2:],
                           config)

    with progress_bar(total=len(pairs), desc="dense stereo") as bar, \
            ThreadPoolExecutor(max_workers=pool_threads(config.workers)) as pool:
        # Results in submission order: the same output for any number of workers.
        for (i, j), (d_i, q_i, d_j, q_j) in zip(pairs, pool.map(one, pairs), strict=True):
            cand_d[i].append(d_i)
            cand_q[i].append(q_i)
            cand_d[j].append(d_j)
            cand_q[j].append(q_j)
            bar.update(1)
    depth, conf, count = [], [], []
    for v in range(n):
        if not cand_d[v]:
            depth.append(np.full((H, W), np.nan))
            conf.append(np.ones((H, W)))
            count.append(np.zeros((H, W), int))
            continue
        d, q = np.stack(cand_d[v]), np.stack(cand_q[v])
        fd, fc = fuse_depth_candidates(d, q, agree_rel_tol=config.agree_rel_tol, conf_max=config.conf_max)
        depth.append(fd)
        conf.append(fc)
        count.append(np.isfinite(d).sum(axis=0))
    return StereoDepths(depth, conf, K, count)
