"""The dense cloud of the chosen solution, and the depth maps' agreement with its cameras.

`reposed` puts the global alignment's depth maps under the bundle-adjusted cameras (rescaled per view onto
the refined tracks, `depth_rescale`); `dense_cloud` recomputes the depth maps by flow stereo with the final
cameras (`mvgeo.align.dense_stereo`, holes filled by `mvgeo.align.hole_fill`), prunes them by
co-visibility and thins them to the point budget (`mvgeo.align.scene`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from mvgeo.align.bundle import BundleResult
from mvgeo.align.dense_stereo import stereo_depths
from mvgeo.align.global_align import GlobalAlignResult
from mvgeo.align.hole_fill import fill_depth_holes
from mvgeo.align.inputs import AlignInputs
from mvgeo.align.pointmap_geometry import pixel_rays
from mvgeo.align.scene import covisibility_keep, pixel_downsample_by_confidence, voxel_downsample_by_confidence
from mvgeo.align.stats import DenseStereoStats
from mvgeo.common.deps import cv2
from mvgeo.common.timing import StageTimer

__all__ = ["DenseCloud", "backproject_depth", "dense_cloud", "depth_rescale", "reposed"]


@dataclass(frozen=True)
class DenseCloud:
    """(P, 3) float64 world points, (P, 3) uint8 colours, (P,) float32 confidences, and the stereo report."""

    xyz: np.ndarray
    rgb: np.ndarray
    conf: np.ndarray
    stereo: DenseStereoStats | None


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


def reposed(res: GlobalAlignResult, cam_from_world: np.ndarray, focal_px: np.ndarray, ba: BundleResult | None = None,
            grid_to_align: float = 1.0) -> tuple[GlobalAlignResult, tuple[np.ndarray, np.ndarray] | None]:
    """The alignment result with new poses/focals; dense points re-projected from the depth maps.

    The bundle adjustment fixes only view 0's pose, so its scene can come out at another scale than the
    global alignment's (and each view's focal can change): depth maps kept as they were would no longer
    agree with the new cameras, and the dense cloud would be smeared across views. With `ba`'s tracks,
    each view's depth map is rescaled by the median ratio of the refined track depths to the map's
    depths at the same pixels (`grid_to_align` = alignment pixels per pointmap pixel).

    Returns:
        (result, (per-view depth scales, their robust spread) or None without tracks).
    """
    depths = [np.asarray(d, float) for d in res.depth]
    rescale = None
    if ba is not None and ba.track_xyz is not None and len(ba.obs_view):
        rescale = depth_rescale(depths, cam_from_world, ba.track_xyz, ba.obs_view, ba.obs_point,
                                ba.obs_uv / grid_to_align)
        depths = [d * k for d, k in zip(depths, rescale[0], strict=True)]
    pts = []
    for v, d in enumerate(depths):
        H, W = d.shape
        R, t = cam_from_world[v][:, :3], cam_from_world[v][:, 3]
        pts.append(((pixel_rays(H, W, float(focal_px[v])) * d[..., None]) - t) @ R)
    out = replace(res, cam_from_world=cam_from_world, focal_px=np.asarray(focal_px, float), pts_world=pts,
                  depth=depths)
    return out, rescale


def _principal(inputs: AlignInputs) -> list[tuple[float, float]]:
    """Per view, the principal point at the alignment size without known intrinsics: the centre, or the one
    the views determined (`mvgeo.align.principal`: K_align without intrinsics)."""
    Wa, Ha = inputs.align_wh
    if inputs.K_align is None:
        return [(Wa / 2.0, Ha / 2.0)] * len(inputs)
    return [(float(K[0, 2]), float(K[1, 2])) for K in np.asarray(inputs.K_align, np.float64)]


def _stereo_maps(inputs: AlignInputs, res: GlobalAlignResult, ba: BundleResult | None, pairs, matches, config,
                 timer: StageTimer, grid_to_align: float, aligned: Callable[[], GlobalAlignResult]):
    """Depth and confidence maps by flow stereo with the final cameras, their grids' K, the masks of their
    measured (not hole-filled) pixels, and the report."""
    Wa, Ha = inputs.align_wh
    with timer.stage("dense_stereo"):
        K_a = (np.asarray(inputs.K_align, np.float64) if inputs.intrinsics is not None  # known: its principal point
               else np.stack([np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]])
                              for f, (cx, cy) in zip(res.focal_px * grid_to_align, _principal(inputs), strict=True)]))
        stereo = stereo_depths(inputs.small, K_a, res.cam_from_world, pairs, {(i, j): uv for i, j, uv in matches},
                               config.dense_stereo)
    depth_maps, conf_maps = list(stereo.depth), list(stereo.conf)
    # A view the stereo leaves (almost) empty (e.g. no baseline to any partner) keeps the global
    # alignment's depth map, resampled onto the stereo grid (same field of view).
    from_alignment = []
    for v, d in enumerate(depth_maps):
        if np.isfinite(d).mean() < config.dense_stereo.min_coverage:
            Hg, Wg = d.shape
            full = aligned()
            depth_maps[v] = cv2.resize(np.asarray(full.depth[v], np.float64), (Wg, Hg), interpolation=cv2.INTER_NEAREST)
            conf_maps[v] = cv2.resize(np.asarray(full.conf[v], np.float64), (Wg, Hg), interpolation=cv2.INTER_NEAREST)
            from_alignment.append(inputs.names[v])
    with timer.stage("hole_fill"):
        depth_maps, conf_maps, filled = fill_depth_holes(depth_maps, conf_maps, config.hole_fill)
    ratio = spread = None
    if ba is not None and ba.track_xyz is not None and len(ba.obs_view):
        # Agreement with the bundle-adjusted tracks (same cameras): median track / stereo depth per view.
        grid = np.array([depth_maps[0].shape[1] / Wa, depth_maps[0].shape[0] / Ha])
        ratio, spread = depth_rescale([np.nan_to_num(d, nan=-1.0) for d in depth_maps], res.cam_from_world,
                                      ba.track_xyz, ba.obs_view, ba.obs_point, ba.obs_uv * grid)
    report = DenseStereoStats(
        size_wh=[int(depth_maps[0].shape[1]), int(depth_maps[0].shape[0])], n_pairs=len(pairs),
        fraction_with_depth=[round(float(np.isfinite(d).mean()), 4) for d in stereo.depth],
        fraction_filled=[round(float(m.mean()), 4) for m in filled], views_with_alignment_depth=from_alignment,
        track_depth_ratio=None if ratio is None else [round(float(k), 4) for k in ratio],
        track_log_mad=None if spread is None else [None if np.isnan(m) else round(float(m), 4) for m in spread])
    return depth_maps, conf_maps, list(stereo.K), [~m for m in filled], report


def dense_cloud(inputs: AlignInputs, res: GlobalAlignResult, ba: BundleResult | None,
                pairs: Sequence[tuple[int, int]], matches: Sequence[tuple[int, int, np.ndarray]], config,
                timer: StageTimer, grid_to_align: float, aligned: Callable[[], GlobalAlignResult]) -> DenseCloud:
    """The output cloud of the chosen solution (module docstring). `config`: `AlignConfig`; `pairs`: the
    pairs with dense pointmaps (the stereo partners); `matches`: every verified pair's matches; `res`: the
    solution (cameras); `aligned`: gives `res` with the depth maps of the full global alignment
    (`mvgeo.align.solve.cloud_alignment`; it may be called more than once and should keep its result), called
    only where the cloud uses them."""
    n = len(inputs)
    report, measured = None, None
    if config.dense_stereo.enabled:
        depth_maps, conf_maps, K_grid, measured, report = _stereo_maps(inputs, res, ba, pairs, matches, config,
                                                                       timer, grid_to_align, aligned)
    else:
        res = aligned()
        depth_maps, conf_maps = res.depth, res.conf
        Hp, Wp = res.depth[0].shape
        Wa, Ha = inputs.align_wh
        if inputs.intrinsics is not None:  # known intrinsics at the pointmap grid (our pixel convention: exact)
            K_grid = [np.diag([Wp / Wa, Hp / Ha, 1.0]) @ K for K in np.asarray(inputs.K_align, np.float64)]
        else:
            K_grid = [np.array([[f, 0, cx * Wp / Wa], [0, f, cy * Hp / Ha], [0, 0, 1]])
                      for f, (cx, cy) in zip(res.focal_px, _principal(inputs), strict=True)]
    # Each pixel's depth goes back along the output camera's own ray (its principal point, known or estimated),
    # so that the cloud and the cameras agree and the co-visibility pruning projects with the same K; the
    # alignment's own points (`res.pts_world`) lie on rays through the grid's centre.
    pts_maps = [backproject_depth(d, k, T) for d, k, T in zip(depth_maps, K_grid, res.cam_from_world, strict=True)]
    with timer.stage("scene"):
        keep = covisibility_keep(pts_maps, depth_maps, conf_maps, res.cam_from_world, K_grid,
                                 rel_depth_tol=config.covisibility_rel_tol,
                                 consistency_rel_tol=config.consistency_rel_tol,
                                 free_space_rel_tol=config.free_space_rel_tol, measured=measured)
        xyz, rgb, conf, pix = [], [], [], []
        for v in range(n):
            Hg, Wg = depth_maps[v].shape
            col = cv2.resize(inputs.images[v], (Wg, Hg), interpolation=cv2.INTER_AREA)
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
    return DenseCloud(xyz[sel], rgb[sel], conf[sel], report)
