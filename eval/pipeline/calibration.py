"""Rounds >= 2 keep the better-determined of two estimates of the same cameras: focal length and poses.

Every round aligns photos of the same camera, but each alignment estimates the
focal length anew from the pairs it verifies. Round 2 sees other images (the
refined ones) and sometimes fewer pairs that determine the focal; on
`llff_like` (default preset, seed 1) its estimate came out 14 % short while
round 1's was within 4 %, and the rebuilt scene lost 0.55 dB held out.

The bundle adjustment reports each estimate's uncertainty (`focal_log_std`, the
standard deviation of log f from its Gauss-Newton covariance). `reuse_intrinsics`
modes (`eval.pipeline.AlignSettings`):

- "auto": align as usual; when the previous round's focal is better determined
  (smaller `focal_log_std`), or this round's alignment refuses for lack of a
  determined focal, align again with the previous round's calibration fixed;
- "always": align with the previous round's calibration fixed (one alignment);
- "never": every round estimates its own (the paper's loop).

The uncertainty travels with a reused calibration (`InheritedCalibration`,
in align.json under `INHERITED_KEY`: `eval.pipeline.align_decisions`), so
round 3 compares against what round 1 measured.

Poses (`reuse_geometry`, `choose_geometry`): round r re-aligns from its K
selected views only, and fewer views pin each camera less; on a real
forward-facing scene round 2's poses came out 0.84 deg off where round 1's were
0.16 deg. "auto" keeps round r's own alignment unless round r-1's determines
the same views better, and then hands round r-1's poses, intrinsics and points
(restricted to the selected views) to round r's splat. "Better determined" is
measured without ground truth, from each alignment's bundle adjustment:

- a view's camera-centre standard deviation with the other cameras held
  (`mvgeo.align.bundle_lm.camera_centre_std`; align.json
  `bundle_adjustment.centre_std_ratio` gives it over the median nearest-neighbour
  distance of that alignment's cameras), re-expressed in units of the median
  nearest-neighbour distance among the selected views in the same alignment,
  so both rounds are measured against the same cameras' spacing;
- the median of that over the selected views: the smaller wins, a tie keeps
  round r's own (`mvgeo.align` writes the ratios to 4 decimals, so figures
  closer than about 1e-4 are ties in effect, decided either way).

Before the figures: round r-1 must hold every selected view (else round r's
own is kept); round r registering fewer of them than round r-1, or its
alignment failing on its geometry (refused as degenerate, or its photos no longer relating every view:
`DisconnectedViewsError`, seen on DTU scan24 at sigma 50 after round 2's re-denoising), hands over
round r-1's; an unknown figure (no bundle adjustment, fewer than 3 views) loses to a known one, and
two unknown keep round r's own. The decision and its numbers go into align.json
under `GEOMETRY_KEY` (`GeometryChoice`, `eval.pipeline.align_decisions`).

Round 1 with `AlignSettings.photos` "better_of" chooses between its noisy and its denoised photos'
alignments by the same figure (`better_determined`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from eval.pipeline.align_decisions import (
    AlignDecisions,
    GeometryChoice,
    InheritedCalibration,
    PerPhotos,
    PhotosComparison,
)
from eval.pipeline.config import ReuseGeometry, ReuseIntrinsics
from mvgeo.align.stats import AlignStats
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.sparse_model import SparseModel, read_sparse_model

__all__ = ["better_determined", "centre_std_over_spacing", "choose_geometry", "focal_log_std", "previous_calibration",
           "prefer_previous", "restricted_ratios"]


def focal_log_std(stats: AlignStats, *, inherited: InheritedCalibration | None) -> float | None:
    """The focal-length uncertainty (std of log f) of an alignment; None when unknown.

    An estimated focal has the bundle adjustment's figure in `stats` (absent without the adjustment); a
    calibration inherited from an earlier round (`stats.known_intrinsics`, `inherited` the align stage's
    record of it) carries that round's figure. A calibration the user gave (`inherited` None) has none.
    """
    if stats.known_intrinsics:
        value = None if inherited is None else inherited.focal_log_std
    else:
        value = None if stats.bundle_adjustment is None else stats.bundle_adjustment.focal_log_std
    if value is None or not np.isfinite(float(value)):
        return None
    return float(value)


def previous_calibration(align_dir: Path) -> tuple[Camera, float | None]:
    """(PINHOLE camera at the input size, its focal log-std or None) of a finished align stage folder.

    The camera is the median of the per-image pinhole parameters (one physical camera; the
    alignment's per-image focals of one round agree to within its noise).

    Raises:
        InputError: the folder lacks `sparse/0/` or `align.json`, or its cameras differ in size.
    """
    align_dir = Path(align_dir)
    stats_file = align_dir / "align.json"
    if not stats_file.is_file():
        raise InputError("the previous round's alignment has no align.json", path=align_dir,
                         fix="re-run the pipeline with --force")
    model = read_sparse_model(align_dir / "sparse" / "0")
    cams = [model.camera_of(n) for n in model.names]
    sizes = {(c.width, c.height) for c in cams}
    if len(sizes) != 1:
        raise InputError(f"the previous round's cameras have several sizes {sorted(sizes)}", path=align_dir)
    (width, height), = sizes
    fx, fy, cx, cy = np.median(np.array([[c.fx, c.fy, c.cx, c.cy] for c in cams]), axis=0)
    stats = AlignStats.read(stats_file)
    inherited = AlignDecisions.read(stats_file).inherited
    return Camera.pinhole(fx, fy, cx, cy, width, height), focal_log_std(stats, inherited=inherited)


def prefer_previous(mode: ReuseIntrinsics, previous_std: float | None, current_std: float | None) -> bool:
    """Whether a round should use the previous round's calibration instead of its own estimate.

    "auto" prefers the previous one only when it is known to be better determined: its
    uncertainty is known and this round's is unknown or larger.
    """
    if mode == "always":
        return True
    if mode == "never" or previous_std is None:
        return False
    return current_std is None or previous_std < current_std


def _nearest_neighbour_spacing(centres: np.ndarray) -> float:
    """Median over cameras of the distance to the nearest other camera; (N, 3) centres, N >= 2."""
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def _centres(model: SparseModel, names: Sequence[str]) -> np.ndarray:
    """(N, 3) camera centres, world frame, of `names` in `model`."""
    out = []
    for n in names:
        cfw = np.asarray(model.image(n).cam_from_world, np.float64)
        out.append(-cfw[:, :3].T @ cfw[:, 3])
    return np.array(out).reshape(-1, 3)


def _ratios(stats: AlignStats, names: Sequence[str]) -> dict[str, float] | None:
    """align.json `bundle_adjustment.centre_std_ratio` by view name, for the model's `names`; None when absent
    or when it does not cover exactly `names`.

    The list follows `bundle_adjustment.views` (the alignment's input order, which `mvgeo.align` takes as
    given: the pipeline's stem order, not the sparse model's name order, e.g. `v.png` before `v-1.png`); an
    align.json written before `views` was recorded has the list in `names` order.
    """
    ba = stats.bundle_adjustment
    ratios = None if ba is None else ba.centre_std_ratio
    if ratios is None:
        return None
    order = list(names) if ba.views is None else list(ba.views)
    if len(ratios) != len(order) or len(set(order)) != len(order) or set(order) != set(names):
        return None
    return {n: float(r) for n, r in zip(order, ratios, strict=True)}


def centre_std_over_spacing(model: SparseModel, stats: AlignStats,
                            views: Sequence[str]) -> dict[str, float] | None:
    """Per view of `views`: its camera-centre standard deviation over the median nearest-neighbour
    distance among the `views` cameras, both in `model`'s frame; None when unknown.

    `stats` is the alignment's align.json; its `bundle_adjustment.centre_std_ratio` lists, in the order of
    `bundle_adjustment.views` (`_ratios`), each centre's std over the median nearest-neighbour distance among
    all of `model`'s cameras (`mvgeo.align`). Unknown: the list is absent or does not match the model, a
    view is not in the model, fewer than 3 views, or the spacing is zero.
    """
    names = list(model.names)
    by_name = _ratios(stats, names)
    if by_name is None or len(views) < 3 or not set(views) <= set(names):
        return None
    spacing_all = _nearest_neighbour_spacing(_centres(model, names))
    spacing_views = _nearest_neighbour_spacing(_centres(model, views))
    if not (spacing_all > 0 and spacing_views > 0):
        return None
    return {v: by_name[v] * spacing_all / spacing_views for v in views}


def restricted_ratios(model: SparseModel, stats: AlignStats, views: Sequence[str]) -> list[float] | None:
    """`bundle_adjustment.centre_std_ratio` of `model` restricted to `views` (in that order): the same
    stds over the restricted cameras' spacing, so that a later round compares against them."""
    per_view = centre_std_over_spacing(model, stats, views)
    return None if per_view is None else [per_view[v] for v in views]


def _median(per_view: Mapping[str, float] | None) -> float | None:
    if per_view is None:
        return None
    value = float(np.median(list(per_view.values())))
    return value if np.isfinite(value) else None


def better_determined(denoised_model: SparseModel, denoised_stats: AlignStats, noisy_model: SparseModel,
                      noisy_stats: AlignStats, views: Sequence[str]) -> tuple[bool, PhotosComparison]:
    """Round 1 with `AlignSettings.photos` "better_of": whether the denoised photos' alignment determines the
    `views`' camera centres better than the noisy photos', and the figures and rule that decided.

    Each alignment's measure is the one `choose_geometry` compares: the median over `views` of
    `centre_std_over_spacing` (no ground truth). An alignment that registers fewer of the views loses; an
    unknown measure keeps the noisy photos' alignment (the "noisy_first" choice).
    """
    counts = PerPhotos(denoised=len(set(views) & set(denoised_model.names)),
                       noisy=len(set(views) & set(noisy_model.names)))
    medians = PerPhotos(denoised=_median(centre_std_over_spacing(denoised_model, denoised_stats, views)),
                        noisy=_median(centre_std_over_spacing(noisy_model, noisy_stats, views)))
    if counts.denoised != counts.noisy:
        keep, why = counts.denoised > counts.noisy, "it registers more of the views"
    elif medians.denoised is None or medians.noisy is None:
        keep, why = False, "a camera-centre uncertainty is unknown: the noisy photos' alignment is kept"
    else:
        keep, why = medians.denoised < medians.noisy, "its camera centres are better determined (bundle adjustment)"
    reason = f"the {'denoised' if keep else 'noisy'} photos' alignment: {why}"
    return keep, PhotosComparison(registered=counts, centre_std_over_spacing=medians, reason=reason)


def choose_geometry(mode: ReuseGeometry, views: Sequence[str], previous: tuple[SparseModel, AlignStats],
                    current: tuple[SparseModel, AlignStats] | None, *,
                    current_error: str | None = None) -> GeometryChoice:
    """Whether a round's splat should start from the previous round's alignment (module docstring's rule).

    Args:
        mode: "auto" applies the rule; "never" always keeps this round's own (the paper's loop).
        views: the round's view names.
        previous: (sparse model, align.json stats) of the previous round's alignment.
        current: the same for this round's alignment; None when it failed (`current_error` says why;
            the caller re-raises that failure when the choice is not the previous round's).
    """
    views = tuple(views)
    prev_model, prev_stats = previous
    prev_names = set(prev_model.names)
    prev_registered = sum(v in prev_names for v in views)
    cur_registered = 0 if current is None else sum(v in set(current[0].names) for v in views)
    prev_std = _median(centre_std_over_spacing(prev_model, prev_stats, views))
    cur_std = None if current is None else _median(centre_std_over_spacing(current[0], current[1], views))

    def decide(used: bool, reason: str) -> GeometryChoice:
        return GeometryChoice(used, reason, views, prev_registered, cur_registered, prev_std, cur_std, current_error)

    if mode == "never":
        return decide(False, "reuse_geometry='never': every round aligns anew (the paper's loop)")
    if current is None:
        if prev_registered < len(views):
            return decide(False, "this round's alignment failed and the previous round's does not hold every view")
        return decide(True, "this round's alignment failed; the previous round's holds every view")
    if prev_registered < len(views):
        return decide(False, "the previous round did not register every selected view")
    if cur_registered < prev_registered:
        return decide(True, "this round registered fewer of the views than the previous round")
    if prev_std is None:
        return decide(False, "the previous round's camera-centre uncertainty is unknown")
    if cur_std is None:
        return decide(True, "this round's camera-centre uncertainty is unknown, the previous round's is known")
    if prev_std < cur_std:
        return decide(True, "the previous round's alignment determines the views' camera centres better")
    return decide(False, "this round's alignment determines the views' camera centres at least as well")
