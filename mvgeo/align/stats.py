"""`AlignStats`: the alignment's report (align.json), typed, with one JSON serializer.

`to_json` writes plain JSON (NaN where a figure does not exist); `from_json` reads it back. A caller that
records its own decisions about an alignment (the `denoise-gs` pipeline) passes them, already JSON, as
`extra_keys` when the file is written: they become top-level keys beside the fields, so align.json stays
one flat document. `from_json` reads the fields only; the caller reads its own keys from the same document
with its own types, so mvgeo never needs to know them.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["AlignStats", "BundleStats", "CandidateSummary", "DenseStereoStats", "FailedPair", "FocalPriorStats",
           "InconsistentPair", "LocatedView", "RejectedPair", "Unregistered"]


@dataclass(frozen=True)
class FailedPair:
    """A pair the pair stage could not relate (or the loop check rejected), by image name."""

    i: str
    j: str
    reason: str


@dataclass(frozen=True)
class RejectedPair:
    """A pair the loop check rejected: how many loops of three pairs it is in contradict / agree with it."""

    i: str
    j: str
    inconsistent_loops: int
    consistent_loops: int


@dataclass(frozen=True)
class Unregistered:
    """A view left out (`AlignConfig.allow_partial`) and why."""

    name: str
    reason: str


@dataclass(frozen=True)
class PrincipalPointStats:
    """The principal point the bundle adjustment estimated for the accepted solution (`mvgeo.align.principal`).

    Attributes:
        offset_px: (x, y) from the image centre, pixels at the input size.
        std_px: its standard deviation (x, y), pixels at the input size.
        kept: whether the output cameras carry it (determined, and the solution with it accepted); else
            they keep the centre.
        reason: the figures that decided.
    """

    offset_px: list[float]
    std_px: list[float]
    kept: bool
    reason: str


@dataclass(frozen=True)
class FocalPriorStats:
    """The focal length the pairs started at without known intrinsics, where not COLMAP's generic prior.

    Attributes:
        source: "exif" (the photos' FocalLengthIn35mmFilm) or "given" (`align_images(focal_prior=...)`).
        focal_35mm: the 35 mm-equivalent focal length (mm).
        focal_px: the same at the input size (pixels).
    """

    source: str
    focal_35mm: float
    focal_px: float


@dataclass(frozen=True)
class InconsistentPair:
    """A verified pair the chosen solution does not explain: the explained fraction of its matches and how far
    the solution's relative rotation is from the one its matches imply (deg; None: not measured)."""

    i: str
    j: str
    explained_fraction: float
    rotation_deviation_deg: float | None


@dataclass(frozen=True)
class LocatedView:
    """A view cut off from the main group by contradicted pairs, checked by PnP on the main group's points
    (`mvgeo.align.locate`): PnP inliers, its rotation's angle from the solution's (deg; None: no pose), the
    points it matched against, and the outcome: "kept" (PnP agrees with the solution), "re-posed" (PnP put
    it elsewhere; the chosen solution was adjusted again from there, `mvgeo.align.solve.relocate`),
    "placed elsewhere" (so, not re-posed), "not located" (too few PnP inliers: refused as before)."""

    name: str
    n_inliers: int
    rotation_deg: float | None
    n_points: int
    outcome: str


@dataclass(frozen=True)
class BundleStats:
    """The bundle adjustment of the chosen solution (pixels at the alignment size)."""

    n_points: int
    n_observations: int
    reproj_rms_before_px: float
    reproj_rms_after_px: float
    reproj_median_before_px: float
    reproj_median_after_px: float
    focal_log_std: float
    solver: str
    #: per view, centre standard deviation / median nearest-camera distance (`verdict.centre_std_ratio`).
    centre_std_ratio: list[float] | None = None
    #: per view, the scale that brought the global alignment's depth map onto the tracks, and its spread.
    dense_depth_scale: list[float] | None = None
    dense_depth_log_mad: list[float | None] | None = None
    #: it ran a second time on the tracks its first result triangulated (`mvgeo.align.bundle.bundle_adjust`).
    readjusted: bool = False
    #: the views the per-view lists above follow (None in an align.json written before it was recorded).
    views: list[str] | None = None


@dataclass(frozen=True)
class DenseStereoStats:
    """The output cloud's depth maps (`mvgeo.align.dense_stereo`)."""

    size_wh: list[int]
    n_pairs: int
    fraction_with_depth: list[float]
    fraction_filled: list[float]
    views_with_alignment_depth: list[str]
    track_depth_ratio: list[float] | None = None
    track_log_mad: list[float | None] | None = None


@dataclass(frozen=True)
class CandidateSummary:
    """One candidate solution the policy solved (`mvgeo.align.policy`), in the order they were solved.

    Attributes:
        start: "chain" or "averaged" (`mvgeo.align.init`).
        pairs_focal_px: the shared focal (alignment px) its pair geometry assumed (None: unknown / per pair).
        bundle_focal_px: the bundle adjustment's median focal (alignment px; None without it).
        refocused: its pairs were recomputed at an earlier candidate's bundle-adjusted focal.
        n_pairs_dropped: verified pairs left out because an earlier candidate did not explain them.
        explained_fraction: fraction of all verified matches its final poses explain.
        reasons: the verdict's reason kinds (empty: accepted).
        chosen: the selection rule kept this one.
        error: the error that stopped it before a verdict (e.g. a disconnected graph), else "".
        start_made_by: how its start's initial values were made (`mvgeo.align.init.initial_values`:
            "chained_pointmaps", "averaged_positions", "averaged_rotations" or "chained_pair_poses").
    """

    start: str
    pairs_focal_px: float | None
    bundle_focal_px: float | None
    refocused: bool
    n_pairs_dropped: int
    explained_fraction: float
    reasons: list[str]
    chosen: bool = False
    error: str = ""
    start_made_by: str = ""


@dataclass
class AlignStats:
    """align.json: what `align_images` did and how well the result fits (sizes as [W, H])."""

    n_images: int
    n_registered: int
    input_size_wh: list[int]
    align_size_wh: list[int]
    pointmap_size_wh: list[int]
    n_pairs: int
    n_pairs_ok: int
    n_pairs_verified: int
    failed_pairs: list[FailedPair]
    pairs_rejected_by_loops: list[RejectedPair]
    unregistered: list[Unregistered]
    iterations: int
    init_loss: float
    final_loss: float
    focal_px: dict[str, float]
    known_intrinsics: bool
    shared_focal: bool
    bundle_adjustment: BundleStats | None
    dense_stereo: DenseStereoStats | None
    focal_determined_by_pairs: bool
    sensitive_features: bool
    initial_poses: str
    candidates: list[CandidateSummary]
    pairs_dropped_as_inconsistent: list[list[str]]
    pair_consistency_min: float
    pairs_inconsistent: list[InconsistentPair]
    n_points: int
    mean_confidence: float
    timings_s: dict[str, float]
    config: dict[str, Any]
    #: None: no prior (known intrinsics, or photos without one EXIF focal: `focal_prior_unavailable` says why).
    focal_prior: FocalPriorStats | None = None
    focal_prior_unavailable: str = ""
    views_located_by_points: list[LocatedView] = field(default_factory=list)
    #: `initial_poses` "auto": the fraction of the verified pairs whose relative rotation the chained start
    #: contradicts, which chose the first start (`mvgeo.align.init.choose_start`; NaN: no pair has a
    #: rotation); else None.
    chain_start_contradicted: float | None = None
    #: None: not estimated (`AlignConfig.principal_point` "centre", known intrinsics, or a refused solution).
    principal_point: PrincipalPointStats | None = None

    def to_json(self, *, extra_keys: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """A JSON-ready dict of the fields, with a caller's `extra_keys` (JSON values) beside them.

        Raises:
            ValueError: an extra key is the name of a field (it would replace the alignment's own figure).
        """
        out = dataclasses.asdict(self)
        extra = dict(extra_keys or {})
        clash = set(extra) & set(out)
        if clash:
            raise ValueError(f"extra keys may not replace align.json fields: {sorted(clash)}")
        return {**out, **extra}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> AlignStats:
        """The inverse of `to_json`: the fields. Keys that are not fields (a caller's `extra_keys`) are left
        out; the caller that wrote them reads them from `data` itself."""
        fields = dataclasses.fields(cls)
        names = {f.name for f in fields}
        # Fields with a default were added later: an older align.json without them still reads.
        required = {f.name for f in fields if f.default is dataclasses.MISSING
                    and f.default_factory is dataclasses.MISSING}
        missing = required - set(data)
        if missing:
            raise KeyError(f"align.json lacks {sorted(missing)}")
        kw = {k: data[k] for k in names if k in data}
        kw["failed_pairs"] = [FailedPair(**x) for x in kw["failed_pairs"]]
        kw["pairs_rejected_by_loops"] = [RejectedPair(**x) for x in kw["pairs_rejected_by_loops"]]
        kw["unregistered"] = [Unregistered(**x) for x in kw["unregistered"]]
        kw["pairs_inconsistent"] = [InconsistentPair(**x) for x in kw["pairs_inconsistent"]]
        kw["candidates"] = [CandidateSummary(**x) for x in kw["candidates"]]
        if kw["bundle_adjustment"] is not None:
            kw["bundle_adjustment"] = BundleStats(**kw["bundle_adjustment"])
        if kw["dense_stereo"] is not None:
            kw["dense_stereo"] = DenseStereoStats(**kw["dense_stereo"])
        kw["views_located_by_points"] = [LocatedView(**x) for x in kw.get("views_located_by_points", [])]
        if kw.get("focal_prior") is not None:
            kw["focal_prior"] = FocalPriorStats(**kw["focal_prior"])
        if kw.get("principal_point") is not None:
            kw["principal_point"] = PrincipalPointStats(**kw["principal_point"])
        return cls(**kw)

    def write(self, path: Path, *, extra_keys: Mapping[str, Any] | None = None) -> None:
        """align.json at `path`: `to_json(extra_keys=extra_keys)`, indented, NaN as NaN."""
        Path(path).write_text(json.dumps(self.to_json(extra_keys=extra_keys), indent=2, allow_nan=True))

    @classmethod
    def read(cls, path: Path) -> AlignStats:
        return cls.from_json(json.loads(Path(path).read_text()))

