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

from mvgeo.align.global_align import GlobalAlignConfig, focal_estimates, init_from_spanning_tree
from mvgeo.align.loops import pair_rotations
from mvgeo.align.pairs import PairPrediction, PairSet
from mvgeo.align.pointmap_geometry import AlignInit, valid_pointmap_pixels
from mvgeo.align.pose_chain import pair_pose_from_pointmap
from mvgeo.align.rotation_averaging import (
    average_rotations,
    init_from_averaged_rotations,
    relative_rotation_residuals_deg,
)
from mvgeo.align.translation_averaging import global_positions
from mvgeo.common.errors import DegenerateGeometryError, UnposedViewsError

__all__ = ["CHAIN_MAX_CONTRADICTED", "STARTS", "chain_contradicted_fraction", "choose_start", "init_from_positions",
           "initial_values", "other_start", "pair_relative_rotations"]

_log = logging.getLogger(__name__)

STARTS = ("chain", "averaged")


#: The "auto" rule's limit on the fraction of the verified pairs the chained start contradicts
#: (`chain_contradicted_fraction`): above it the averaged start goes first. Measured
#: (`benchmarks/diag_chain_start.py`, docs/bench/align.md): the temple ring 0.88 (its chained candidate is
#: refused, 68 deg off); at most 0.50 on every other real and synthetic scene at the defaults (object_ring
#: 0.50, hard_repetitive 0.44, hard_tinybaseline 0.27, DTU scan24 0-0.39, llff_like 0); 0.56-0.62 on the
#: noisy temple's groups that `allow_partial` keeps (docs/bench/real_subsets.md).
CHAIN_MAX_CONTRADICTED = 2.0 / 3.0


def choose_start(initial_poses: str, chain_contradicted: float | None = None) -> str:
    """The first start: `initial_poses` itself unless "auto".

    The "auto" rule: DUSt3R's chaining first, unless the chained start contradicts most of the pairs
    (`chain_contradicted`, the fraction of the verified pairs whose own relative rotation is more than
    `AlignConfig.max_pair_rotation_deg` from the chained start's, above `CHAIN_MAX_CONTRADICTED`): the
    averaged start (rotation averaging, then global positioning) goes first then. The other start is the
    second start where the first contradicts its pairs as a whole or its focal keeps drifting
    (`mvgeo.align.policy`, `AlignConfig.second_start`).

    Why chaining first: measured each start alone (docs/bench/align.md, `benchmarks/diag_align_init.py`), the
    averaged start is the more accurate on most synthetic scenes (llff_like 0.011 against 0.014 deg; with
    `allow_partial`, object_ring 12/12 against 9/12 views and the temple 12/12 against 6/12). But it returns
    wrong models no check refuses where chaining is refused or right: on object_ring's 21 training views at
    256x192 (24-view ring, 15-30 deg steps) all 21 views at a median of 1.2-3.0 deg, max 15-16 deg (which of
    refused and accepted it gives there flips with small changes of its own start: the global positioning's
    tolerance, the PnP pixels), where chaining is refused naming the views; on its 28 training views of 32
    accepted with a view 22 deg off, where chaining is right (0.41 deg); and first on ten noise draws of DTU
    scan24 (`bench_real.py --methods=ours_averaged`, docs/bench/real_partial_draws.md) one draw with a view
    10.6 deg off (two of its four pairs explained it: one of them, 96 matches, is itself 10 deg off), where
    chaining first is right on all ten. A named refusal or a right model is preferred to a faster wrong one.

    Why the exception: a chained start that contradicts most pairs is a wrong Procrustes compounded along the
    tree, which neither the global alignment (it moves the rotations by about a degree) nor the bundle
    adjustment recovers from: on the temple ring its candidate is refused after both, 68 deg off, and
    solving it cost 0.8 s of a 2.8 s alignment before the averaged start (1.0 deg) was solved anyway. Where
    chaining is kept first the chained start contradicts at most half of the pairs, and the pairs it
    contradicts are often themselves wrong (repeated texture).

    Args:
        initial_poses: "auto", "chain" or "averaged".
        chain_contradicted: `chain_contradicted_fraction` of the chained start, or None (not measured:
            chaining first).
    """
    if initial_poses != "auto":
        return initial_poses
    if chain_contradicted is not None and chain_contradicted > CHAIN_MAX_CONTRADICTED:
        return "averaged"
    return "chain"


def chain_contradicted_fraction(cam_from_world: np.ndarray, rotations: dict[tuple[int, int], np.ndarray],
                                max_pair_rotation_deg: float) -> float:
    """Fraction of the pairs whose own relative rotation is more than `max_pair_rotation_deg` from the one the
    poses imply (`rotation_averaging.relative_rotation_residuals_deg`); NaN without pairs.

    Args:
        cam_from_world: (N, 3, 4) poses (a start's initial values).
        rotations: (i, j) -> (3, 3) cam_j_from_cam_i rotation of each verified pair (`pair_relative_rotations`).
    """
    if not rotations:
        return float("nan")
    off = relative_rotation_residuals_deg(np.asarray(cam_from_world, np.float64)[:, :, :3], rotations)
    return float(np.mean([d > max_pair_rotation_deg for d in off.values()]))


def pair_relative_rotations(pairs: PairSet, K_align: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """cam_j_from_cam_i rotation of every pair: the pair model's own relative pose where it has one
    (`PairGeometry.cam_j_from_cam_i`), else from the pair's matches or pointmap (`loops.pair_rotations`).

    Args:
        pairs: the `PairSet`; K_align: (N, 3, 3) intrinsics at the alignment resolution (for the pairs
            without a pose).

    Returns:
        (i, j) with i < j -> (3, 3).
    """
    rel: dict[tuple[int, int], np.ndarray] = {}
    for g in pairs.geometries:
        if g.cam_j_from_cam_i is not None:
            R = np.asarray(g.cam_j_from_cam_i, np.float64)[:, :3]
            rel[(g.i, g.j) if g.i < g.j else (g.j, g.i)] = R if g.i < g.j else R.T
    rest = [(g.i, g.j, g.matches_px) for g in pairs.geometries if g.cam_j_from_cam_i is None]
    preds = [p for p in pairs.predictions if (min(p.i, p.j), max(p.i, p.j)) not in rel]
    if rest or preds:
        more, _ = pair_rotations(rest, K_align, preds)
        rel.update({k: v for k, v in more.items() if k not in rel})
    return rel


def other_start(start: str) -> str:
    """The start a second attempt uses."""
    return "averaged" if start == "chain" else "chain"


def initial_values(start: str, pairs: PairSet, sizes_hw: Sequence[tuple[int, int]], focal_init_px: np.ndarray | None,
                   align: GlobalAlignConfig, grid_to_align: float, align_wh: tuple[int, int]
                   ) -> tuple[GlobalAlignConfig, AlignInit | None, str]:
    """The global alignment's config and initial values for `start`, and how they were made.

    "chain" is DUSt3R's start: the pairs' pointmaps chained by Procrustes along a maximum spanning tree
    (`global_align.init_from_spanning_tree`; made by "chained_pointmaps"). "averaged" takes the first of
    these that succeeds, each a weaker use of the same pairs:

    1. "averaged_positions": rotation averaging, then global positioning of the cameras on the tracks
       (`translation_averaging.global_positions`), each view's depths from its strongest pair;
    2. "averaged_rotations": the averaged rotations with positions chained from the pairs' own translations
       (`init_from_averaged_rotations`; where the tracks do not determine the positions);
    3. "chained_pair_poses": init None, so that `global_align` chains the pairs' own relative poses
       (`pose_chain.init_from_pair_poses`; where the rotations do not connect the views).

    Args:
        start: "chain" or "averaged".
        pairs: the candidate's pairs; sizes_hw: pointmap grid per view.
        focal_init_px: (N,) known focals on the pointmap grid, or None (the pairs' estimates).
        align: the configured `GlobalAlignConfig`; grid_to_align: alignment pixels per grid pixel.

    Returns:
        (config, init, made_by): init None lets `global_align` initialise itself (config.init says how);
        made_by names the way above, recorded in the candidate's summary (`AlignStats.candidates`).

    Raises:
        DegenerateGeometryError: the chained start cannot chain or pose a view.
    """
    n = len(sizes_hw)
    f = focal_init_px if focal_init_px is not None else focal_estimates(pairs.predictions, n)
    if focal_init_px is None and align.shared_focal:
        f = np.full(n, float(np.exp(np.mean(np.log(f)))))
    f = np.asarray(f, float)
    if start == "chain":
        init = init_from_spanning_tree(pairs.predictions, sizes_hw, focal_init_px=f)
        return replace(align, init="procrustes"), init, "chained_pointmaps"
    align = replace(align, init="pair_poses")
    W, H = align_wh
    K = np.array([[[fv * grid_to_align, 0.0, W / 2.0], [0.0, fv * grid_to_align, H / 2.0], [0.0, 0.0, 1.0]]
                  for fv in f])
    try:
        rel, weight = pair_rotations(pairs.matches, K, pairs.predictions)
        R = average_rotations(n, rel, weight).R_cam_from_world
        placed = global_positions(R, K, pairs.matches)
        return align, init_from_positions(pairs.predictions, sizes_hw, placed.cam_from_world, f), "averaged_positions"
    except DegenerateGeometryError as exc:
        _log.warning("rotation averaging and global positioning gave no start (%s); chaining the pairs' poses", exc)
    try:
        return align, init_from_averaged_rotations(pairs.predictions, pairs.matches, sizes_hw, f, grid_to_align,
                                                   align_wh), "averaged_rotations"
    except DegenerateGeometryError as exc:
        _log.warning("rotation averaging gave no initialisation (%s); chaining the pairs' own poses", exc)
        return align, None, "chained_pair_poses"


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
        raise UnposedViewsError("no pair with a usable pointmap and baseline", views=missing)
    return AlignInit(np.asarray(cam_from_world, np.float64).copy(), np.asarray(focal_px, np.float64).copy(), depth)
