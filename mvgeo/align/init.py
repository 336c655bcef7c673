"""Initial poses of a candidate solution: DUSt3R's chaining or GLOMAP-style averaging, and the rule between them.

- "chain": DUSt3R's initialisation. The pairs' pointmaps are chained along the maximum spanning tree of
  the pair confidences with weighted Procrustes, then each view is posed by PnP on its chained points
  (`global_align.init_from_spanning_tree`). Exact on a tree; on a graph with loops the last pair of each
  loop carries the drift, and with narrow fields of view a Procrustes rotation between two differently
  distorted pointmaps of one view can be tens of degrees off.
- "averaged": GLOMAP's approach. Rotation averaging over every verified pair
  (`rotation_averaging.average_rotations`), then the camera centres by global positioning on the feature
  tracks with those rotations (`translation_averaging.global_positions`); each view's depth map comes from
  its strongest pair's pointmap, scaled so that the pair's baseline is the positioned one
  (`init_from_positions`). Every loop constrains the rotations and every track the positions; there is
  no tree to compound errors along. Where the positioning fails (e.g. no baseline), the positions are
  chained along the tree from the pairs' own translation directions (`init_from_averaged_rotations`).

`choose_start` is the stated rule for `AlignConfig.initial_poses = "auto"`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from mvgeo.align.global_align import GlobalAlignConfig, focal_estimates
from mvgeo.align.loops import pair_rotations
from mvgeo.align.pairs import PairPrediction, PairSet
from mvgeo.align.pointmap_geometry import AlignInit, pair_similarities, valid_pointmap_pixels
from mvgeo.align.pose_chain import pair_pose_from_pointmap
from mvgeo.align.rotation_averaging import average_rotations, init_from_averaged_rotations
from mvgeo.align.translation_averaging import global_positions
from mvgeo.common.errors import DegenerateGeometryError

__all__ = ["STARTS", "choose_start", "init_from_positions", "initial_values", "other_start"]

_log = logging.getLogger(__name__)

STARTS = ("chain", "averaged")


def choose_start(initial_poses: str, pairs: PairSet, n_views: int) -> str:
    """The first start: `initial_poses` itself unless "auto".

    The "auto" rule: DUSt3R's chaining first, the averaged start (rotation averaging, then global positioning)
    as the second start where the first contradicts its pairs as a whole or its focal keeps drifting
    (`mvgeo.align.policy`, `AlignConfig.second_start`). Measured each start alone (docs/bench/align.md,
    `benchmarks/diag_align_init.py`): the averaged start is the more accurate on most synthetic scenes
    (llff_like 0.011 against 0.014 deg; with `allow_partial`, object_ring 12/12 against 9/12 views and the
    temple 12/12 against 6/12) and saves the chained candidate on the temple ring (1.9 s against 2.8 s). But
    it returns wrong models no check refuses where chaining is refused or right: on object_ring's 21 training
    views at 256x192 (24-view ring, 15-30 deg steps) all 21 views at a median of 1.2-3.0 deg, max 15-16 deg
    (which of refused and accepted it gives there flips with small changes of its own start: the global
    positioning's tolerance, the PnP pixels), where chaining is refused naming the views; and first on ten
    noise draws of DTU scan24 (`bench_real.py --methods=ours_averaged`, docs/bench/real_partial_draws.md)
    one draw with a view 10.6 deg off (two of its four pairs explained it: one of them, 96 matches, is itself
    10 deg off), where chaining first is right on all ten. A named refusal or a right model is preferred to
    a faster wrong one, so chaining stays first.
    """
    del pairs, n_views
    return "chain" if initial_poses == "auto" else initial_poses


def other_start(start: str) -> str:
    """The start a second attempt uses."""
    return "averaged" if start == "chain" else "chain"


def initial_values(start: str, pairs: PairSet, sizes_hw: Sequence[tuple[int, int]], focal_init_px: np.ndarray | None,
                   align: GlobalAlignConfig, grid_to_align: float, align_wh: tuple[int, int]
                   ) -> tuple[GlobalAlignConfig, AlignInit | None]:
    """The global alignment's config and initial values for `start`.

    Args:
        start: "chain" or "averaged".
        pairs: the candidate's pairs; sizes_hw: pointmap grid per view.
        focal_init_px: (N,) known focals on the pointmap grid, or None (the pairs' estimates).
        align: the configured `GlobalAlignConfig`; grid_to_align: alignment pixels per grid pixel.

    Returns:
        (config, init): init None lets `global_align` initialise itself (config.init says how).
    """
    if start == "chain":
        return replace(align, init="procrustes"), None
    align = replace(align, init="pair_poses")
    n = len(sizes_hw)
    f = focal_init_px if focal_init_px is not None else focal_estimates(pairs.predictions, n)
    if focal_init_px is None and align.shared_focal:
        f = np.full(n, float(np.exp(np.mean(np.log(f)))))
    f = np.asarray(f, float)
    W, H = align_wh
    K = np.array([[[fv * grid_to_align, 0.0, W / 2.0], [0.0, fv * grid_to_align, H / 2.0], [0.0, 0.0, 1.0]]
                  for fv in f])
    try:
        rel, weight = pair_rotations(pairs.matches, K, pairs.predictions)
        R = average_rotations(n, rel, weight).R_cam_from_world
        placed = global_positions(R, K, pairs.matches)
        return align, init_from_positions(pairs.predictions, sizes_hw, placed.cam_from_world, f)
    except DegenerateGeometryError as exc:
        _log.warning("rotation averaging and global positioning gave no start (%s); chaining the pairs' poses", exc)
    try:
        return align, init_from_averaged_rotations(pairs.predictions, pairs.matches, sizes_hw, f, grid_to_align,
                                                   align_wh)
    except DegenerateGeometryError as exc:
        _log.warning("rotation averaging gave no initialisation (%s); chaining the pairs' own poses", exc)
        return align, None


def init_from_positions(preds: Sequence[PairPrediction], sizes_hw: Sequence[tuple[int, int]],
                        cam_from_world: np.ndarray, focal_px: np.ndarray) -> AlignInit:
    """Initial values with the poses given: each view's depth map from its strongest pair's pointmap.

    A pair's pointmap is in camera i's frame at the pair's own scale; its relative pose
    (`pose_chain.pair_pose_from_pointmap`) gives the pair's baseline in those units, and the given poses the
    baseline in the world: their ratio scales the pair's depths. Pixels without a confident point get the
    median depth (as DUSt3R's initialisation).

    Args:
        preds: the pairs' pointmaps; sizes_hw: pointmap grid per view.
        cam_from_world: (N, 3, 4) the poses; focal_px: (N,) focals on the pointmap grid.

    Raises:
        DegenerateGeometryError: a view has no pair with a usable pointmap and a baseline.
    """
    n = len(sizes_hw)
    C = np.stack([-T[:, :3].T @ T[:, 3] for T in cam_from_world])
    depth: list[np.ndarray | None] = [None] * n
    for p in sorted(preds, key=lambda q: -q.score):
        if depth[p.i] is not None and depth[p.j] is not None:
            continue
        pose = pair_pose_from_pointmap(p, float(focal_px[p.j]))
        if pose is None:
            continue
        R_ji, t_ji = pose
        base_pair, base_world = float(np.linalg.norm(t_ji)), float(np.linalg.norm(C[p.i] - C[p.j]))
        if not (base_pair > 0 and base_world > 0):
            continue
        for v, z, conf, pts in ((p.i, p.pts_i[..., 2], p.conf_i, p.pts_i),
                                (p.j, (p.pts_j.astype(np.float64) @ R_ji.T + t_ji)[..., 2], p.conf_j, p.pts_j)):
            if depth[v] is not None:
                continue
            z = np.asarray(z, np.float64) * (base_world / base_pair)
            ok = valid_pointmap_pixels(conf, pts) & (z > 0) & np.isfinite(z)
            if not np.any(ok):
                continue
            med = float(np.median(z[ok]))
            depth[v] = np.where(ok & (z > 1e-3 * med), z, med)
    missing = [v for v in range(n) if depth[v] is None]
    if missing:
        raise DegenerateGeometryError(f"views {missing} have no pair with a usable pointmap and baseline")
    return AlignInit(np.asarray(cam_from_world, np.float64).copy(), np.asarray(focal_px, np.float64).copy(), depth,
                     pair_similarities(preds, sizes_hw, cam_from_world, depth, focal_px))
