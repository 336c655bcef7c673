"""One candidate solution: the checked pair graph, then global alignment, bundle adjustment and the verdict.

`pair_graph` turns the pair stage's `PairSet` into the graph a candidate is solved on: pairs whose relative
rotation contradicts most of their loops of three pairs are rejected (`mvgeo.align.loops`), and the views
must be connected (or, with `allow_partial`, the largest connected group is kept). `solve` runs one start
(`mvgeo.align.init`) through the global alignment (`AlignConfig.candidate_align_iters` of its iterations
where set) and the bundle adjustment on every verified pair's matches, and judges the result against all
of them (`mvgeo.align.verdict`). `cloud_alignment` runs the global alignment in full for the chosen
candidate's cloud where the candidate ran fewer iterations.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np

from mvgeo.align.bundle import BundleResult, bundle_adjust
from mvgeo.align.checks import PairCheck, views_cut_off, views_hinged
from mvgeo.align.cloud import reposed
from mvgeo.align.global_align import GlobalAlignConfig, GlobalAlignResult, focal_estimates, global_align
from mvgeo.align.graph import components
from mvgeo.align.init import initial_values
from mvgeo.align.inputs import AlignInputs
from mvgeo.align.locate import LOCATE_MAX_ROTATION_DEG, Located, locate_cut_off
from mvgeo.align.loops import pair_rotations, reject_by_loops, rotation_angle_deg
from mvgeo.align.pairs import PairFailure, PairSet
from mvgeo.align.pointmap_geometry import AlignInit
from mvgeo.align.stats import FailedPair, RejectedPair, Unregistered
from mvgeo.align.verdict import Verdict, judge_pairs, verdict
from mvgeo.common.errors import DisconnectedViewsError, UnposedViewsError
from mvgeo.common.timing import StageTimer

__all__ = ["Candidate", "PairGraph", "StartValues", "adjust_and_judge", "cloud_alignment", "main_group_change_deg",
           "pair_graph", "pairs_K_align", "prior_confirmed", "relocate", "solve", "start_values"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairGraph:
    """The pairs a candidate is solved on (after the loop check), restricted to the views to register.

    Attributes:
        inputs: the registered views; pairs: their pairs, renumbered.
        failed: every pair that failed or was rejected, by name; rejected: the loop check's rejections.
        unregistered: views left out because no usable pair connects them (`allow_partial`).
        refocused: how many times the pairs were recomputed at a bundle-adjusted focal.
    """

    inputs: AlignInputs
    pairs: PairSet
    failed: list[FailedPair]
    rejected: list[RejectedPair]
    unregistered: list[Unregistered]
    refocused: int = 0

    @property
    def grid_to_align(self) -> float:
        """Alignment pixels per pointmap pixel."""
        return self.inputs.align_wh[0] / self.pairs.predictions[0].pts_i.shape[1]


def pairs_K_align(inputs: AlignInputs, pairs: PairSet) -> np.ndarray:
    """(N, 3, 3) intrinsics at the alignment resolution: the known ones, else the pairs' focal estimates
    (pointmap pixels -> alignment pixels) with the principal point at the centre."""
    if inputs.K_align is not None:
        return inputs.K_align
    preds = pairs.predictions
    Hp, Wp = preds[0].pts_i.shape[:2]
    s = inputs.align_wh[0] / Wp
    return np.array([[[f, 0, Wp * s / 2.0], [0, f, Hp * s / 2.0], [0, 0, 1]]
                     for f in focal_estimates(preds, len(inputs)) * s])


def _loop_check(inputs: AlignInputs, pairs: PairSet, config) -> tuple[PairSet, list[tuple[tuple[int, int], int, int]]]:
    preds = pairs.predictions
    rel, weight = pair_rotations(pairs.matches, pairs_K_align(inputs, pairs), preds)
    loop = reject_by_loops(rel, weight, max_loop_deg=config.max_loop_deg)
    if not loop.removed:
        return pairs, []
    _log.warning("loop check: %d of %d loops of three pairs are inconsistent; rejected pairs %s",
                 loop.n_inconsistent, loop.n_triangles,
                 [(inputs.names[i], inputs.names[j]) for i, j in sorted(loop.removed)])
    gone = {(min(i, j), max(i, j)) for i, j in loop.removed}
    kept = replace(pairs, predictions=[p for p in preds if (min(p.i, p.j), max(p.i, p.j)) not in gone],
                   geometries=[g for g in pairs.geometries if (min(g.i, g.j), max(g.i, g.j)) not in gone],
                   failures=pairs.failures + [PairFailure(i, j, "rejected by the loop check") for i, j in loop.removed])
    return kept, [(e, b, g) for e, (b, g) in zip(loop.removed, loop.votes, strict=True)]


def pair_graph(inputs: AlignInputs, pairs: PairSet, config, timer: StageTimer, *, refocused: int = 0) -> PairGraph:
    """Loop check and connectivity (module docstring). `config`: `AlignConfig`.

    Raises:
        DisconnectedViewsError: the pairs do not connect the views (without `allow_partial`), naming them.
    """
    names = inputs.names
    failed = [FailedPair(names[f.i], names[f.j], f.reason) for f in pairs.failures]
    rejected = []
    if config.loop_check and pairs.predictions:
        with timer.stage("loop_check"):
            pairs, votes = _loop_check(inputs, pairs, config)
        for (i, j), bad, good in votes:
            rejected.append(RejectedPair(names[i], names[j], bad, good))
            failed.append(FailedPair(names[i], names[j], f"rejected: its relative rotation contradicts {bad} of the "
                                                         f"{bad + good} loops of three pairs it is in"))
    comps = components(len(inputs), [(p.i, p.j) for p in pairs.predictions])
    main = comps[0]
    if len(comps) > 1 and not (config.allow_partial and len(main) >= 2):
        lost = [names[v] for c in comps[1:] for v in c]
        reasons = "; ".join(f"({names[f.i]}, {names[f.j]}): {f.reason}" for f in pairs.failures
                            if (f.i in main) != (f.j in main))[:2000]
        raise DisconnectedViewsError(
            f"the pair graph is disconnected: images {lost} could not be related to {[names[v] for v in main]}"
            + (f". Failed pairs: {reasons}" if reasons else ""), views=lost,
            fix=("no two images could be related: check that they show one scene with enough overlap and texture"
                 if len(main) < 2 else "add views that overlap the disconnected ones, or remove them; try --pairs "
                 "complete; or pass --allow-partial to register only the largest connected group"))
    unregistered = []
    if len(main) < len(inputs):
        unregistered = [Unregistered(names[v], "not connected to the registered images by any usable pair")
                        for v in range(len(inputs)) if v not in main]
        _log.warning("registering %d of %d images (--allow-partial); not connected: %s", len(main), len(inputs),
                     [u.name for u in unregistered])
        inputs, pairs = inputs.restricted(main), pairs.restricted(main)
    return PairGraph(inputs, pairs, failed, rejected, unregistered, refocused)


@dataclass
class Candidate:
    """One solved start (see `mvgeo.align.policy` for how candidates are generated and chosen).

    Attributes:
        start: "chain" or "averaged"; graph: the pair graph it derives from.
        inputs, pairs: the views and pairs it was solved with (the graph's, less dropped pairs and views).
        result: the global alignment, re-posed by the bundle adjustment when it ran.
        ba: the bundle adjustment, or None; depth_rescale: per-view depth scales onto its tracks.
        align_config: the global alignment's config.
        checks, bad: every verified pair of the registered views (dropped ones included) against the result.
        dropped: pairs (by name) left out because an earlier candidate did not explain them.
        unregistered: views left out, with the reason (the graph's and the dropped ones).
        verdict: the reasons to refuse it (none: accepted).
        located: the views cut off by contradicted pairs, each with its PnP on the main group's points
            (`mvgeo.align.locate`); those it locates are not refused.
        relocated: the views `relocate` moved to their PnP pose before this candidate's adjustment.
        start_values: the start's initial values, from which `cloud_alignment` runs the global alignment
            in full (None where the candidate ran it in full already).
        start_made_by: how the start's initial values were made (`StartValues.made_by`).
    """

    start: str
    graph: PairGraph
    inputs: AlignInputs
    pairs: PairSet
    result: GlobalAlignResult
    ba: BundleResult | None
    depth_rescale: tuple[np.ndarray, np.ndarray] | None
    align_config: GlobalAlignConfig
    checks: list[PairCheck]
    bad: list[PairCheck]
    dropped: list[tuple[str, str]] = field(default_factory=list)
    unregistered: list[Unregistered] = field(default_factory=list)
    verdict: Verdict = Verdict()
    located: list[Located] = field(default_factory=list)
    relocated: list[Located] = field(default_factory=list)
    start_values: StartValues | None = None
    start_made_by: str = ""

    @property
    def explained_fraction(self) -> float:
        """Fraction of the verified matches the result explains (1 without matches)."""
        total = sum(c.n_matches for c in self.checks)
        return 1.0 if not total else sum(c.n_matches * c.explained_fraction for c in self.checks) / total

    @property
    def bundle_focal_px(self) -> float | None:
        """The bundle adjustment's median focal (alignment px), or None without it."""
        return None if self.ba is None else float(np.median(self.ba.focal_px))


@dataclass(frozen=True)
class StartValues:
    """One start's global-alignment config and initial values (`mvgeo.align.init.initial_values`).

    Attributes:
        start: "chain" or "averaged"; align_config: the global alignment's config for it.
        init: the initial values, or None (`global_align` initialises itself, as `align_config.init` says).
        focal_init_px: (N,) known focals on the pointmap grid, or None (estimated from the pairs).
        made_by: how the values were made (`mvgeo.align.init.initial_values`).
    """

    start: str
    align_config: GlobalAlignConfig
    init: AlignInit | None
    focal_init_px: np.ndarray | None
    made_by: str = ""


@contextmanager
def naming_views(names: Sequence[str]) -> Iterator[None]:
    """Inside the block, an `UnposedViewsError` (raised with view indices) is raised again naming the views."""
    try:
        yield
    except UnposedViewsError as exc:
        if exc.names is not None:
            raise
        raise exc.naming(names) from None


def start_values(graph: PairGraph, start: str, config, *, inputs: AlignInputs | None = None,
                 pairs: PairSet | None = None) -> StartValues:
    """`start`'s initial values on the graph's views and pairs (or the given ones). `config`: `AlignConfig`.

    Raises:
        DegenerateGeometryError: the start cannot pose a view.
    """
    inputs = graph.inputs if inputs is None else inputs
    with naming_views(inputs.names):
        return _start_values(graph, start, config, inputs, graph.pairs if pairs is None else pairs)


def _start_values(graph: PairGraph, start: str, config, inputs: AlignInputs, pairs: PairSet) -> StartValues:
    n = len(inputs)
    Hp, Wp = pairs.predictions[0].pts_i.shape[:2]
    focal_init = None
    align_cfg = config.align
    if inputs.intrinsics is not None:  # known calibration: fx at the pointmap grid (square pixels assumed)
        W0, H0 = inputs.input_wh
        focal_init = np.full(n, 0.5 * (inputs.intrinsics.fx * Wp / W0 + inputs.intrinsics.fy * Hp / H0))
        align_cfg = replace(align_cfg, optimize_focal=False)
    align_cfg, init, made_by = initial_values(start, pairs, [(Hp, Wp)] * n, focal_init, align_cfg,
                                              graph.grid_to_align, inputs.align_wh)
    return StartValues(start, align_cfg, init, focal_init, made_by)


def solve(graph: PairGraph, start: str, config, timer: StageTimer, *, inputs: AlignInputs | None = None,
          pairs: PairSet | None = None, dropped: list[tuple[str, str]] | None = None,
          unregistered: list[Unregistered] | None = None, values: StartValues | None = None) -> Candidate:
    """Global alignment from `start`, bundle adjustment, verdict. `inputs`/`pairs` default to the graph's
    (a pruned candidate passes fewer); `values`: `start`'s initial values on exactly these views and pairs
    when already computed (`start_values`); `config`: `AlignConfig`."""
    inputs = graph.inputs if inputs is None else inputs
    pairs = graph.pairs if pairs is None else pairs
    Hp, Wp = pairs.predictions[0].pts_i.shape[:2]
    with timer.stage("global_align"), naming_views(inputs.names):
        if values is None:
            values = start_values(graph, start, config, inputs=inputs, pairs=pairs)
        elif values.start != start:
            raise ValueError(f"initial values of the {values.start} start given for the {start} start")
        run_cfg, later = values.align_config, None
        fewer = config.candidate_align_iters
        if fewer is not None and fewer < run_cfg.iters and config.bundle_adjust and pairs.geometries:
            # The poses are the bundle adjustment's: the start goes to it after `candidate_align_iters`
            # iterations, and the full alignment runs only for the chosen candidate's cloud.
            run_cfg, later = replace(run_cfg, iters=fewer), values
        res = global_align(pairs.predictions, [(Hp, Wp)] * len(inputs), config=run_cfg,
                           focal_init_px=values.focal_init_px, init=values.init)
    c = adjust_and_judge(graph, start, res, values.align_config, config, timer, inputs=inputs, pairs=pairs,
                         dropped=dropped, unregistered=unregistered)
    return replace(c, start_values=later, start_made_by=values.made_by)


def cloud_alignment(c: Candidate, timer: StageTimer) -> GlobalAlignResult:
    """`c`'s result with the depth maps of its global alignment run in full (`AlignConfig.align.iters`) from
    its start's initial values, re-posed onto its bundle adjustment (`mvgeo.align.cloud.reposed`): the
    poses and focals are `c.result`'s. `c.result` itself where the candidate ran the alignment in full."""
    v = c.start_values
    if v is None or c.ba is None:
        return c.result
    Hp, Wp = c.pairs.predictions[0].pts_i.shape[:2]
    with timer.stage("global_align"):
        res = global_align(c.pairs.predictions, [(Hp, Wp)] * len(c.inputs), config=v.align_config,
                           focal_init_px=v.focal_init_px, init=v.init)
        s = c.graph.grid_to_align
        return reposed(res, c.result.cam_from_world, c.result.focal_px, c.ba, s)[0]


def ideal_pixels(uv_px: np.ndarray, K: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """(M, 2) pixels `uv_px` of a view with known intrinsics `K` (alignment pixels) as the camera the bundle
    adjustment, the pair checks and PnP model sees them: principal point at the image centre, square pixels
    of focal `K[0, 0]`. Exact for a pinhole `K` (the same rays)."""
    W, H = size_wh
    uv = np.asarray(uv_px, np.float64)
    return np.stack([uv[:, 0] - K[0, 2] + W / 2.0, (uv[:, 1] - K[1, 2]) * (K[0, 0] / K[1, 1]) + H / 2.0], axis=1)


def ideal_matches(matches: Sequence[tuple[int, int, np.ndarray]], K_align: np.ndarray | None,
                  size_wh: tuple[int, int]) -> list[tuple[int, int, np.ndarray]]:
    """`matches` ((i, j, (M, 4) uv)) through `ideal_pixels` of their views (`K_align[i]`, `K_align[j]`); as
    they are without known intrinsics (the principal point is then taken at the centre anyway)."""
    if K_align is None:
        return list(matches)
    return [(i, j, np.hstack([ideal_pixels(uv[:, :2], K_align[i], size_wh), ideal_pixels(uv[:, 2:], K_align[j],
                                                                                          size_wh)]))
            for i, j, uv in matches]


@dataclass(frozen=True)
class _IdealKeypoints:
    """A view's keypoints through `ideal_pixels` (the `Keypoints` protocol: `uv_px`, `root()`)."""

    uv_px: np.ndarray
    base: object

    def root(self) -> np.ndarray:
        return self.base.root()


def adjust_and_judge(graph: PairGraph, start: str, res: GlobalAlignResult, align_cfg: GlobalAlignConfig, config,
                     timer: StageTimer, *, inputs: AlignInputs, pairs: PairSet,
                     dropped: list[tuple[str, str]] | None = None, unregistered: list[Unregistered] | None = None,
                     relocated: Sequence[Located] = ()) -> Candidate:
    """Bundle adjustment from `res`'s poses, then the verdict (`solve`'s second half; `relocate` starts it
    from re-posed views)."""
    n, s = len(inputs), graph.grid_to_align
    ba, rescale = None, None
    if config.bundle_adjust and pairs.geometries:
        with timer.stage("bundle_adjust"):
            ba_cfg = replace(config.bundle, shared_focal=config.bundle.shared_focal or align_cfg.shared_focal,
                             optimize_focal=inputs.intrinsics is None)
            ba = bundle_adjust(res.cam_from_world, res.focal_px * s, inputs.align_wh,
                               ideal_matches(pairs.matches, inputs.K_align, inputs.align_wh), config=ba_cfg)
            res, rescale = reposed(res, ba.cam_from_world, ba.focal_px / s, ba, s)
    # Judged against every verified pair of these views, the dropped ones included. Without the bundle
    # adjustment the poses come from pointmaps `s` times coarser than the matches: judged at that resolution.
    keep = {name: k for k, name in enumerate(inputs.names)}
    index = [keep.get(name) for name in graph.inputs.names]
    evidence = ideal_matches([(index[i], index[j], uv) for i, j, uv in graph.pairs.matches
                              if index[i] is not None and index[j] is not None], inputs.K_align, inputs.align_wh)
    thr = config.consistency_px * (1.0 if ba is not None else max(s, 1.0))
    feats = None
    if graph.pairs.features is not None:  # per view of `inputs`, like the evidence's indices
        feats = [None] * n
        for k, i in enumerate(index):
            if i is not None:
                f = graph.pairs.features[k]
                feats[i] = f if inputs.K_align is None else _IdealKeypoints(
                    ideal_pixels(f.uv_px, inputs.K_align[i], inputs.align_wh), f)
    checks, bad = judge_pairs(res.cam_from_world, res.focal_px * s, inputs.align_wh, evidence, threshold_px=thr,
                              min_explained=config.min_pair_explained, max_rotation_deg=config.max_pair_rotation_deg)
    located: list[Located] = []
    if ba is not None and feats is not None and config.reject_unsupported_views and config.locate_cut_off_views:
        cut = sorted(set(views_cut_off(checks, bad, n)) | set(views_hinged(checks, bad, n)))
        if cut:
            with timer.stage("locate"):
                located = locate_cut_off(res.cam_from_world, res.focal_px * s, inputs.align_wh, feats, checks, bad,
                                         cut)
            _log.info("views cut off by contradicted pairs or held by one pair, located by PnP on the main group's "
                      "points (view: inliers, deg from the solution): %s", ", ".join(
                          f"{inputs.names[x.view]}: {x.n_inliers}, {x.rotation_deg:.2f}" for x in located))
    # A focal prior (EXIF) the bundle adjustment keeps within `refocus_min_change` determines the focal as
    # well as agreeing pairs do: the data do not contradict it. Only for pairs computed at the prior: pairs
    # re-estimated at an adjusted focal exist because an adjustment moved the focal away from the prior, so
    # a later adjustment that lands near it again is not the prior confirmed (measured on the noisy temple
    # ring, noise seed 1, --allow-partial: prior 1516 px, adjusted 1302 px, then 1373 px from the
    # re-estimated pairs, 9.7 % from the truth and 5.5 % uncertain, which this rule accepted with six views
    # 4-15 deg off).
    prior = pairs.focal_prior_px
    prior_kept = ba is not None and prior_confirmed(prior, pairs.focal_px, float(np.median(ba.focal_px)),
                                                    config.refocus_min_change)
    judged = verdict(checks, bad, inputs.names, ba=ba,
                     focal_determined=pairs.focal_determined or inputs.intrinsics is not None or prior_kept,
                     focal_undetermined_why=pairs.focal_undetermined_why, config=config,
                     focal_prior_used=prior is not None, located_views=[x.view for x in located if x.ok],
                     misplaced_views=[x.view for x in located if x.placed_elsewhere])
    return Candidate(start, graph, inputs, pairs, res, ba, rescale, align_cfg, checks, bad, list(dropped or []),
                     list(graph.unregistered) + list(unregistered or []), judged, located, list(relocated))


def prior_confirmed(prior_px: float | None, pairs_focal_px: float | None, adjusted_focal_px: float,
                    max_log_change: float) -> bool:
    """Whether the bundle adjustment confirms a focal prior: the pairs were computed at the prior (not
    re-estimated at an adjusted focal) and the adjustment kept the focal within `max_log_change` (log) of it."""
    if prior_px is None or pairs_focal_px is None:
        return False
    return (abs(float(np.log(pairs_focal_px / prior_px))) <= 1e-6
            and abs(float(np.log(adjusted_focal_px / prior_px))) <= max_log_change)


def relocate(c: Candidate, config, timer: StageTimer) -> Candidate | None:
    """`c` adjusted again with the views its verdict cut off that PnP on the main group's points places
    confidently elsewhere (`Located.placed_elsewhere`) moved to the PnP pose; None without such views, or
    when the adjustment turns any relative rotation among the other views by more than
    `LOCATE_MAX_ROTATION_DEG` (`main_group_change_deg`): it then bent the views whose points located them.

    The contradicted pairs that cut such a view off are the evidence of its wrong placement: the bundle
    adjustment from the global alignment's start settled it in a wrong minimum that its weak pairs could
    not pull it out of (measured: DTU scan24, sigma 25/255, noise seed 8 with the calibration given, a view
    64 deg off with 137 PnP inliers).
    """
    moved = [x for x in c.located if x.placed_elsewhere]
    if not moved or c.ba is None:
        return None
    poses = np.array(c.result.cam_from_world, copy=True)
    for x in moved:
        poses[x.view] = x.cam_from_world
    _log.warning("re-posing %s where PnP on the main group's points puts them, and adjusting again",
                 [c.inputs.names[x.view] for x in moved])
    new = adjust_and_judge(c.graph, c.start, replace(c.result, cam_from_world=poses), c.align_config, config, timer,
                           inputs=c.inputs, pairs=c.pairs, dropped=c.dropped,
                           unregistered=c.unregistered[len(c.graph.unregistered):], relocated=moved)
    # The PnP poses stand on the other views' points: an adjustment that moves those views' relative rotations
    # by more than a PnP's own tolerance has bent what located the view (measured on object_ring's 28 views
    # with raw pair poses: a ring bent at its loop closure, re-posed there, came back bent by 6.5 deg
    # throughout, max 22 deg, all pairs explained; DTU: 0.09 deg, sigma-50 photos 0.8 deg).
    bend = main_group_change_deg(c.result.cam_from_world, new.result.cam_from_world, {x.view for x in moved})
    if bend > LOCATE_MAX_ROTATION_DEG:
        _log.warning("re-posing moved the other views' relative rotations by up to %.1f deg: not kept", bend)
        return None
    # its views' depth maps come from the same start
    return replace(new, start_values=c.start_values, start_made_by=c.start_made_by)


def main_group_change_deg(before: np.ndarray, after: np.ndarray, moved: set[int]) -> float:
    """The largest change (deg) of a relative rotation between two views not in `moved`."""
    keep = [v for v in range(len(before)) if v not in moved]
    worst = 0.0
    for k, a in enumerate(keep):
        for b in keep[k + 1:]:
            r0 = before[b][:, :3] @ before[a][:, :3].T
            r1 = after[b][:, :3] @ after[a][:, :3].T
            worst = max(worst, rotation_angle_deg(r1 @ r0.T))
    return worst
