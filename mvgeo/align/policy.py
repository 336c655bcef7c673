"""Candidate solutions, and the one rule that chooses among them.

A candidate is one start solved on one pair graph (`mvgeo.align.solve`). Candidates are generated in this
order, at most `AlignConfig.max_candidates` in all; each candidate adds the successors it calls for, and
generation ends when no candidate calls for one:

1. the first start (`mvgeo.align.init.choose_start`; for "auto" it measures the chained start's initial values
   against the pairs, and those values are reused when chaining goes first) on the pair graph. The averaged
   start's own fallbacks (global positioning, then chained positions, then the chained pair poses) are
   `mvgeo.align.init.initial_values`'s, recorded as each candidate's `start_made_by`;
2. focal re-estimation: without known intrinsics, a candidate whose bundle adjustment moved the shared
   focal by more than `refocus_min_change` (log) from the focal its pairs assumed is not self-consistent:
   the pair geometry is computed again at the adjusted focal from the same features and matches
   (`RefocusableModel.refocus`) and the same start solved on it, up to `MAX_REFOCUS` times in a row (a
   fixed-point iteration: pairs computed at a focal far from the truth pull the adjustment only part of
   the way; measured on DTU scan24, prior 443 px -> 838 px -> 941 px; from a wrong well-determined pair
   focal, noise seed 4 of the benchmark: 259 -> 3896 -> 2084 -> 967 -> 962 px, where two re-estimations
   left a candidate that explained 98 % of the matches with a focal still moving, and the drifting other
   start was chosen, 28 deg off);
3. pruning: a candidate with contradicted pairs is solved again without them, where that keeps the views
   connected (with `allow_partial`: keeping the largest connected group, and also leaving out the views
   whose positions the tracks do not determine); once, or three times with `allow_partial`. It is still
   judged against every verified pair, the dropped ones included. Accepted candidates are pruned too, of the
   pairs whose matches they do not explain (`min_pair_explained`; `_prunable`): on object_ring's 28 training
   views of 32 (256x192) the accepted, self-consistent candidate is bent (5.8 deg median, 22 deg max; its
   contradicted pairs hold under `max_unexplained_fraction` of the matches) and its pruning is right (0.52
   deg). A pair that fails only the rotation check is not pruned from an accepted candidate: it explains
   its matches, which leave the rotation ambiguous. Pruned of such pairs too, 8 accepted candidates of 32
   real and synthetic sets and 2 of 8 dithers of object_ring (`benchmarks/diag_accepted_prune.py`: DTU
   scan24 clusters and the temple ring's layouts, clean and sigma 25/255, six noise draws of the DTU
   cluster, object_ring, llff_like) came back with the same result on nine and a worse one on one (worst
   pair 0.97 against 0.92 deg), at 0.3-2.9 s each;
4. relocation (`mvgeo.align.solve.relocate`), before pruning: a candidate whose verdict cuts off views that
   PnP on the main group's points places confidently elsewhere (`mvgeo.align.locate`), and locates all the
   others where the candidate has them, is adjusted again from the PnP poses, once;
5. second start (`second_start`), once: a candidate that contradicts its pairs as a whole
   (`max_unexplained_fraction`: a wrong minimum, not one weak view) is solved from the other start on its
   unpruned graph; and when the first start's candidates are exhausted, all refused or accepted ones whose
   focal still moves after `MAX_REFOCUS` re-estimations, the other start is solved on the first pair graph.
   Measured on noisy DTU scan24 with ratio 0.85 matching: the averaged start's focal drifted 256 -> 194 ->
   168 -> 110 px (truth 925 px) through re-estimations whose results each explained 86-89 % of the matches
   and were not refused; the chained start settles at 929 px, 0.28 deg, 99.3 % explained. On object_ring's 28
   training views of 32 under dithers of 0.5/255 (seeds 3 and 7), the chained start's candidates bent the
   ring (views 4-19 deg off) and were refused as cut off or hinged, each explaining most of the matches; the
   averaged start registers all 28 views at 0.37-0.41 deg median, 1.3 deg at worst
   (`benchmarks/diag_refused_second_start.py`).

Selection rule: the candidate with the highest (accepted by its verdict, self-consistent focal, views
registered, fraction of all verified matches explained). The views count only with `allow_partial`, where a
pruned candidate may leave views out: an accepted candidate that keeps a view (e.g. one PnP located where the
candidate has it) wins over its pruning that drops it, whatever the pruning explains (measured on noisy DTU
scan24, noise seed 0: 12 views at 0.30 deg against 11). If the chosen candidate is not accepted,
`align_images` raises its verdict's first reason. A successor that fails outright (e.g. refocused pairs that
no longer connect the views) is recorded and skipped.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from mvgeo.align.checks import unconfirmed_hinged
from mvgeo.align.graph import components
from mvgeo.align.init import chain_contradicted_fraction, choose_start, other_start, pair_relative_rotations
from mvgeo.align.inputs import AlignInputs
from mvgeo.align.pairs import PairSet, PointmapModel, RefocusableModel
from mvgeo.align.solve import (
    Candidate,
    PairGraph,
    StartValues,
    pair_graph,
    pairs_K_align,
    relocate,
    solve,
    start_values,
)
from mvgeo.align.stats import CandidateSummary, Unregistered
from mvgeo.align.verdict import loose_views, mostly_unexplained
from mvgeo.common.errors import DegenerateGeometryError, InputError, UnposedViewsError
from mvgeo.common.timing import StageTimer

__all__ = ["MAX_REFOCUS", "choose_solution"]

#: Focal re-estimations in a row at most (item 2 of the module docstring).
MAX_REFOCUS = 3

_log = logging.getLogger(__name__)


def _focal_consistent(c: Candidate, config) -> bool:
    """The candidate's pairs assumed (about) the focal its bundle adjustment found; True where that cannot
    be re-estimated (known intrinsics, no bundle adjustment, a model without one focal)."""
    f_pairs, f_ba = c.pairs.focal_px, c.bundle_focal_px
    if c.inputs.intrinsics is not None or f_pairs is None or f_ba is None or config.refocus_min_change <= 0:
        return True
    return abs(np.log(f_ba / f_pairs)) <= config.refocus_min_change


def _rank(c: Candidate, config) -> tuple:
    return (c.verdict.ok, _focal_consistent(c, config), len(c.inputs), c.explained_fraction)


def _relocatable(c: Candidate) -> bool:
    """PnP places some of `c`'s cut-off views elsewhere and locates the rest where `c` has them: re-posing can
    lift the refusal (a view PnP cannot locate would still be cut off). Once per lineage."""
    return (not c.relocated and any(x.placed_elsewhere for x in c.located)
            and all(x.ok or x.placed_elsewhere for x in c.located))


def _prunable(c: Candidate, config) -> set[tuple[int, int]]:
    """The contradicted pairs `c` would be solved again without, among those it was solved with: every failing
    pair of a refused candidate; of an accepted one, only the pairs whose matches it does not explain
    (`min_pair_explained`). A pair that fails only the rotation check is explained by the result: its matches
    leave the rotation ambiguous (the check's reason), and solving again without it did not change the chosen
    solution in any measured case (module docstring, item 3)."""
    present = {(p.i, p.j) for p in c.pairs.predictions} | {(g.i, g.j) for g in c.pairs.geometries}
    bad = c.bad if not c.verdict.ok else [b for b in c.bad if b.explained_fraction < config.min_pair_explained]
    return {(b.i, b.j) for b in bad} & present


def _pruned(c: Candidate, config, timer: StageTimer) -> Candidate | None:
    """`c` solved again without its contradicted pairs (`_prunable`; and, with `allow_partial`, its undetermined
    views)."""
    gone = _prunable(c, config)
    loose = set(loose_views(c.ba, config.max_centre_std_ratio)) if config.allow_partial else set()
    unsupported: set[int] = set()
    if config.allow_partial and config.reject_unsupported_views:  # views held by one pair PnP does not confirm
        unsupported = set(unconfirmed_hinged(c.checks, c.bad, len(c.inputs), [x.view for x in c.located if x.ok],
                                             [x.view for x in c.located if x.placed_elsewhere])) - loose
        loose |= unsupported
    if not gone and not loose:
        return None
    pairs = c.pairs.without_pairs(gone)
    comps = components(len(c.inputs), [(p.i, p.j) for p in pairs.predictions if p.i not in loose and p.j not in loose])
    if len(comps) > 1 and not config.allow_partial:
        return None  # dropping them would cut views off: the candidate is judged as it is
    keep = comps[0]
    if len(keep) < 2:
        return None
    names = c.inputs.names
    lost = [Unregistered(names[v], "its pose is not supported by its pairs nor by PnP on the others' points"
                         if v in unsupported else "its position is not determined by the feature tracks" if v in loose
                         else "its pairs are inconsistent with the reconstruction of the others")
            for v in range(len(names)) if v not in keep]
    dropped = c.dropped + sorted((names[i], names[j]) for i, j in gone)
    _log.warning("solving again without %d pairs the result does not explain %s%s", len(gone),
                 [(names[i], names[j]) for i, j in sorted(gone)], f" and without views {[u.name for u in lost]}"
                 if lost else "")
    return solve(c.graph, c.start, config, timer, inputs=c.inputs.restricted(keep), pairs=pairs.restricted(keep),
                 dropped=dropped, unregistered=c.unregistered[len(c.graph.unregistered):] + lost)


def _refocused(c: Candidate, inputs: AlignInputs, pair_list: Sequence[tuple[int, int]], model: PointmapModel,
               config, timer: StageTimer) -> Candidate | None:
    f_ba = c.bundle_focal_px
    _log.warning("the bundle adjustment moved the focal from %.1f to %.1f px: computing the pairs again with it",
                 c.pairs.focal_px, f_ba)
    with timer.stage("pairwise"):
        again = model.refocus(inputs.small, pair_list, f_ba)
    # Whether the pairs determine the focal does not change with the focal they are computed at.
    again = replace(again, focal_determined=c.graph.pairs.focal_determined,
                    focal_undetermined_why=c.graph.pairs.focal_undetermined_why,
                    focal_prior_px=c.graph.pairs.focal_prior_px)
    return solve(pair_graph(inputs, again, config, timer, refocused=c.graph.refocused + 1), c.start, config, timer)


def _exhausted_start(done: Sequence[Candidate], config) -> bool:
    """The first start's candidates ran out without settling: every one refused, or accepted ones whose focal
    still moves after `MAX_REFOCUS` re-estimations (a drifting focal, not weak data). The other start is then
    solved on the first pair graph (item 5 of the module docstring)."""
    drifting = any(k.verdict.ok and not _focal_consistent(k, config) and k.graph.refocused >= MAX_REFOCUS
                   for k in done)
    return drifting or not any(k.verdict.ok for k in done)


def _summary(c: Candidate) -> CandidateSummary:
    f_pairs = None if c.pairs.focal_px is None else round(c.pairs.focal_px, 2)
    return CandidateSummary(start=c.start, pairs_focal_px=f_pairs,
                            bundle_focal_px=None if c.ba is None else round(c.bundle_focal_px, 2),
                            refocused=c.graph.refocused > 0, n_pairs_dropped=len(c.dropped),
                            explained_fraction=round(c.explained_fraction, 4),
                            reasons=[r.kind for r in c.verdict.reasons], start_made_by=c.start_made_by)


def _first_start(graph: PairGraph, config, timer: StageTimer) -> tuple[str, float | None, StartValues | None]:
    """(first start, the fraction of the pairs the chained start contradicts or None, the chained start's
    initial values on the graph or None): `choose_start`'s rule on the graph. Where the chained start cannot
    pose every view (its pointmaps do not connect them, though the verified pairs do), the averaged start
    goes first, with None for the fraction (a chained second start on this graph then fails the same way and
    is recorded as a failed candidate)."""
    if config.initial_poses != "auto":
        return choose_start(config.initial_poses), None, None
    with timer.stage("global_align"):
        try:
            chain = start_values(graph, "chain", config)
        except UnposedViewsError as exc:
            _log.warning("the chained start cannot be built (%s): the averaged start goes first", exc)
            return "averaged", None, None
        rotations = pair_relative_rotations(graph.pairs, pairs_K_align(graph.inputs, graph.pairs))
        contradicted = chain_contradicted_fraction(chain.init.cam_from_world, rotations,
                                                   config.max_pair_rotation_deg)
    first = choose_start("auto", contradicted)
    if first != "chain":
        _log.warning("the chained start contradicts %.0f %% of the pairs' relative rotations (by more than %g "
                     "deg): the %s start goes first", 100 * contradicted, config.max_pair_rotation_deg, first)
    return first, contradicted, chain


def choose_solution(inputs: AlignInputs, pairs: PairSet, pair_list: Sequence[tuple[int, int]], model: PointmapModel,
                    config, timer: StageTimer) -> tuple[Candidate, list[CandidateSummary], float | None]:
    """Generate candidates and choose one (module docstring). `config`: `AlignConfig`.

    Returns:
        (the chosen candidate, a summary of every candidate in the order solved, the chosen one marked;
        the fraction of the pairs the chained start contradicts, which chose the first start; None unless
        "auto").

    Raises:
        DisconnectedViewsError: the pair graph is disconnected (without `allow_partial`; an `InputError`).
        DegenerateGeometryError: the chosen candidate is refused by its verdict, or the first start fails.
    """
    graph: PairGraph = pair_graph(inputs, pairs, config, timer)
    first, contradicted, chain = _first_start(graph, config, timer)

    def values(g: PairGraph, start: str) -> StartValues | None:  # the chained start measured on `graph`, reused
        return chain if start == "chain" and g is graph else None

    done: list[Candidate] = [solve(graph, first, config, timer, values=values(graph, first))]
    summaries = [_summary(done[0])]
    pending = [done[0]]
    prunes: dict[int, int] = {id(done[0]): 0}
    max_prunes = 3 if config.allow_partial else 1
    def settled(c: Candidate) -> bool:  # accepted, self-consistent, and nothing left to prune
        return (c.verdict.ok and _focal_consistent(c, config)
                and not (_prunable(c, config) and prunes[id(c)] < max_prunes))

    second_tried = False
    while len(summaries) < config.max_candidates and not any(settled(c) for c in done):
        if not pending:
            if second_tried or not config.second_start or not _exhausted_start(done, config):
                break
            second_tried = True
            root = done[0]
            other = other_start(root.start)
            makers = [(other, lambda root=root, other=other: solve(root.graph, other, config, timer,
                                                                  values=values(root.graph, other)), False)]
            c = root
        else:
            c = pending.pop(0)
            if (_focal_consistent(c, config) or c.graph.refocused >= MAX_REFOCUS
                    or not isinstance(model, RefocusableModel)):
                # Pairs at the right focal (or no way to recompute them): prune, then the other start.
                makers = [(c.start, lambda c=c: _pruned(c, config, timer), True)] if prunes[id(c)] < max_prunes else []
                if _relocatable(c):
                    makers.insert(0, (c.start, lambda c=c: relocate(c, config, timer), False))
                if (config.second_start and not second_tried and c.start == first and not c.dropped
                        and mostly_unexplained(c.checks, c.bad, config.max_unexplained_fraction)):
                    second_tried = True
                    makers.append((other_start(c.start), lambda c=c: solve(
                        c.graph, other_start(c.start), config, timer, values=values(c.graph, other_start(c.start))),
                        False))
            else:  # the pairs assumed a focal the bundle adjustment rejects: recompute them first
                makers = [(c.start, lambda c=c: _refocused(c, inputs, pair_list, model, config, timer), False)]
        # (the start the successor is solved from, the successor, whether it is a pruning: a relocation or a
        # refocus does not use up the prunings, so an accepted relocated candidate is still pruned)
        for start, make, is_pruning in makers:
            if len(summaries) >= config.max_candidates:
                break
            try:
                new = make()
            except (InputError, DegenerateGeometryError) as exc:
                summaries.append(CandidateSummary(start, None, None, False, 0, 0.0, [], error=str(exc)[:300]))
                continue
            if new is None:
                continue
            if new.start != c.start:
                _log.warning("the %s start did not settle; solved from the %s start", c.start, new.start)
                prunes[id(new)] = 0
            else:
                prunes[id(new)] = prunes[id(c)] + int(is_pruning)
            done.append(new)
            summaries.append(_summary(new))
            pending.append(new)
            if settled(new):
                break
    best = max(range(len(done)), key=lambda k: _rank(done[k], config))
    chosen = done[best]
    position = [k for k, s in enumerate(summaries) if not s.error][best]
    summaries[position] = replace(summaries[position], chosen=True)
    _log.info("candidates: %s; chose %d", [(s.start, s.reasons, s.explained_fraction) for s in summaries], position)
    if not chosen.verdict.ok:
        raise chosen.verdict.error()
    return chosen, summaries, contradicted
