"""The align stage's own records about an alignment, typed, and where they live in align.json.

`mvgeo.align` reports an alignment in its `AlignStats`. The `denoise-gs` align stage decides more than
mvgeo knows about: which photos round 1 aligned (`PhotosDecision`), whether a round >= 2 keeps its own
poses or the previous round's (`GeometryChoice`), and whether it took the previous round's calibration
(`InheritedCalibration`). `AlignDecisions` holds them; `AlignStageResult` carries them next to the
`AlignResult` they describe, from the alignment to the writer.

On disk each record is one top-level key of align.json beside `AlignStats`' fields (`PHOTOS_KEY`,
`GEOMETRY_KEY`, `INHERITED_KEY`): the stage writes `AlignDecisions.to_json()` as
`write_align_result(..., extra_keys=...)`, and `AlignDecisions.read` reads them back from the same file
(`AlignStats.from_json` leaves them out). Each record's `to_json` writes the keys and values it always
has, an optional one only where it is set, so that run folders written before these types read alike.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

from eval.pipeline.config import ReuseIntrinsics
from mvgeo.align.result import AlignResult
from mvgeo.align.writer import write_align_result

__all__ = ["GEOMETRY_KEY", "INHERITED_KEY", "PHOTOS_KEY", "AlignDecisions", "AlignStageResult", "AlignedPhotos",
           "FocalEstimate", "GeometryChoice", "InheritedCalibration", "PerPhotos", "PhotosComparison",
           "PhotosDecision"]

#: align.json key of round 1's record of which photos it aligned (`AlignSettings.photos`).
PHOTOS_KEY = "aligned_photos"
#: align.json key of the rounds >= 2 decision between this round's poses and the previous round's.
GEOMETRY_KEY = "geometry_from_previous_round"
#: align.json key of a round whose calibration was offered by the previous round (`reuse_intrinsics`).
INHERITED_KEY = "intrinsics_from_previous_round"

#: Whose poses round 1's alignment holds: the noisy photos' or the denoised photos'.
AlignedPhotos = Literal["noisy", "denoised"]


def _optional_float(value: object) -> float | None:
    return None if value is None else float(value)


@dataclass(frozen=True)
class PerPhotos[T]:
    """One figure for each of round 1's two alignments, the denoised photos' and the noisy photos'."""

    denoised: T
    noisy: T

    def of(self, photos: AlignedPhotos) -> T:
        """The figure of the `photos` alignment."""
        return self.denoised if photos == "denoised" else self.noisy

    def to_json(self) -> dict[str, T]:
        return {"denoised": self.denoised, "noisy": self.noisy}

    @classmethod
    def from_json(cls, data: Mapping[str, T]) -> PerPhotos[T]:
        return cls(denoised=data["denoised"], noisy=data["noisy"])


@dataclass(frozen=True)
class PhotosComparison:
    """Round 1 with `AlignSettings.photos` "better_of", both photos aligned: what chose between them
    (`eval.pipeline.calibration.better_determined`).

    Attributes:
        registered: how many of the views each alignment registered.
        centre_std_over_spacing: each alignment's median over the views of the camera-centre std in units of
            the views' median nearest-neighbour spacing (`centre_std_over_spacing`); None where unknown.
        reason: the alignment kept and the rule that kept it, in words.
    """

    registered: PerPhotos[int]
    centre_std_over_spacing: PerPhotos[float | None]
    reason: str

    def to_json(self) -> dict[str, object]:
        return {"registered": self.registered.to_json(),
                "centre_std_over_spacing": self.centre_std_over_spacing.to_json(), "reason": self.reason}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> PhotosComparison:
        registered = data["registered"]
        stds = data["centre_std_over_spacing"]
        return cls(registered=PerPhotos(int(registered["denoised"]), int(registered["noisy"])),
                   centre_std_over_spacing=PerPhotos(_optional_float(stds["denoised"]),
                                                     _optional_float(stds["noisy"])),
                   reason=str(data["reason"]))


@dataclass(frozen=True)
class PhotosDecision:
    """Round 1: which photos the alignment holds (align.json `PHOTOS_KEY`; `AlignSettings.photos`).

    Attributes:
        aligned: "noisy": the noisy photos' poses (under the denoised photos' names; the dense cloud from the
            denoised photos); "denoised": the denoised photos' poses.
        noisy_refused: the noisy photos' refusal (its first line), where they were tried and refused.
        denoised_refused: the denoised photos' refusal, where the noisy ones aligned and these were refused.
        comparison: "better_of" with both photos aligned: the figures that chose between them.
        identical: the denoised photos held the noisy photos' pixels (passed through undenoised), so the
            photos were aligned once (`eval.pipeline.align_stage.same_photos`).

    In JSON `comparison`'s keys sit beside `aligned` (one flat record); an unset optional is left out.
    """

    aligned: AlignedPhotos
    noisy_refused: str | None = None
    denoised_refused: str | None = None
    comparison: PhotosComparison | None = None
    identical: bool = False

    def __post_init__(self) -> None:
        if self.aligned not in get_args(AlignedPhotos):
            raise ValueError(f"PhotosDecision.aligned must be one of {get_args(AlignedPhotos)}, not {self.aligned!r}")

    def to_json(self) -> dict[str, object]:
        out: dict[str, object] = {"aligned": self.aligned}
        if self.comparison is not None:
            out.update(self.comparison.to_json())
        if self.noisy_refused is not None:
            out["noisy_refused"] = self.noisy_refused
        if self.denoised_refused is not None:
            out["denoised_refused"] = self.denoised_refused
        if self.identical:
            out["identical_photos"] = True
        return out

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> PhotosDecision:
        return cls(aligned=data["aligned"], noisy_refused=data.get("noisy_refused"),
                   denoised_refused=data.get("denoised_refused"),
                   comparison=PhotosComparison.from_json(data) if "registered" in data else None,
                   identical=bool(data.get("identical_photos", False)))


@dataclass(frozen=True)
class GeometryChoice:
    """A round's choice between its own alignment and the previous round's, for the same views
    (align.json `GEOMETRY_KEY`; `eval.pipeline.calibration.choose_geometry`).

    Attributes:
        used_previous: True: the round's splat starts from the previous round's poses, intrinsics and points.
        reason: the rule that decided, in words.
        views: the round's (selected) view names.
        previous_registered, current_registered: how many of `views` each alignment registered
            (current: 0 when this round's alignment failed).
        previous_centre_std, current_centre_std: median over `views` of the camera-centre std in units of
            their median nearest-neighbour spacing (`centre_std_over_spacing`); None when unknown.
        current_error: this round's alignment error message, when it failed.
    """

    used_previous: bool
    reason: str
    views: tuple[str, ...]
    previous_registered: int
    current_registered: int
    previous_centre_std: float | None
    current_centre_std: float | None
    current_error: str | None = None

    def to_json(self) -> dict[str, object]:
        """Every field, `views` as a list and `current_error` null where unset."""
        d = dataclasses.asdict(self)
        d["views"] = list(self.views)
        return d

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> GeometryChoice:
        return cls(used_previous=bool(data["used_previous"]), reason=str(data["reason"]),
                   views=tuple(data["views"]), previous_registered=int(data["previous_registered"]),
                   current_registered=int(data["current_registered"]),
                   previous_centre_std=_optional_float(data["previous_centre_std"]),
                   current_centre_std=_optional_float(data["current_centre_std"]),
                   current_error=data.get("current_error"))


@dataclass(frozen=True)
class FocalEstimate:
    """A round's own focal estimate: the median focal over its images (px at the input size) and its
    uncertainty (std of log f from the bundle adjustment); None where unknown."""

    focal_px: float | None
    focal_log_std: float | None

    def to_json(self) -> dict[str, float | None]:
        return {"focal_px": self.focal_px, "focal_log_std": self.focal_log_std}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> FocalEstimate:
        return cls(_optional_float(data["focal_px"]), _optional_float(data["focal_log_std"]))


@dataclass(frozen=True)
class InheritedCalibration:
    """Rounds >= 2 with `reuse_intrinsics` "auto" or "always": the previous round's calibration, offered to
    this round, and what the round did with it (align.json `INHERITED_KEY`; `eval.pipeline.calibration`).

    Attributes:
        focal_px: the previous round's focal (mean of fx and fy of its median camera; px at the input size).
        focal_log_std: its uncertainty (std of log f), as the previous round measured or inherited it; None:
            unknown. A later round compares against it (`focal_log_std`).
        mode: the `reuse_intrinsics` mode ("auto" or "always").
        used: True: this round aligned with the previous round's calibration fixed.
        estimate_refused: "auto": this round's own alignment was refused (the error, 500 characters at most),
            so the calibration was used.
        estimate_discarded: "auto": this round's own estimate, less well determined, so not used (`used`).
        estimate_focal_log_std: "auto", this round's own estimate kept (`used` False): its uncertainty
            (None: unknown). Written only then.
    """

    focal_px: float
    focal_log_std: float | None
    mode: ReuseIntrinsics
    used: bool
    estimate_refused: str | None = None
    estimate_discarded: FocalEstimate | None = None
    estimate_focal_log_std: float | None = None

    def __post_init__(self) -> None:
        if self.used and self.estimate_focal_log_std is not None:
            raise ValueError("InheritedCalibration: estimate_focal_log_std belongs to a round that kept its own "
                             "estimate (used=False)")
        if not self.used and (self.estimate_refused is not None or self.estimate_discarded is not None):
            raise ValueError("InheritedCalibration: a refused or discarded estimate means the calibration was "
                             "used (used=True)")

    def to_json(self) -> dict[str, object]:
        out: dict[str, object] = {"focal_px": self.focal_px, "focal_log_std": self.focal_log_std,
                                  "mode": self.mode}
        if self.estimate_refused is not None:
            out["estimate_refused"] = self.estimate_refused
        if self.estimate_discarded is not None:
            out["estimate_discarded"] = self.estimate_discarded.to_json()
        out["used"] = self.used
        if not self.used:
            out["estimate_focal_log_std"] = self.estimate_focal_log_std
        return out

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> InheritedCalibration:
        discarded = data.get("estimate_discarded")
        return cls(focal_px=float(data["focal_px"]), focal_log_std=_optional_float(data["focal_log_std"]),
                   mode=data["mode"], used=bool(data["used"]), estimate_refused=data.get("estimate_refused"),
                   estimate_discarded=None if discarded is None else FocalEstimate.from_json(discarded),
                   estimate_focal_log_std=_optional_float(data.get("estimate_focal_log_std")))


@dataclass(frozen=True)
class AlignDecisions:
    """The align stage's records about one alignment; None where the stage did not make that decision.

    Attributes:
        photos: round 1: which photos were aligned (a round >= 2 that hands over round 1's alignment keeps it).
        geometry: rounds >= 2: this round's poses or the previous round's.
        inherited: rounds >= 2 with `reuse_intrinsics`: the previous round's calibration and its use.
    """

    photos: PhotosDecision | None = None
    geometry: GeometryChoice | None = None
    inherited: InheritedCalibration | None = None

    def to_json(self) -> dict[str, object]:
        """The top-level align.json keys of the records that are set."""
        out: dict[str, object] = {}
        if self.photos is not None:
            out[PHOTOS_KEY] = self.photos.to_json()
        if self.geometry is not None:
            out[GEOMETRY_KEY] = self.geometry.to_json()
        if self.inherited is not None:
            out[INHERITED_KEY] = self.inherited.to_json()
        return out

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> AlignDecisions:
        """The records in an align.json document (`data`: all of it; the other keys are `AlignStats`')."""
        photos, geometry, inherited = (data.get(k) for k in (PHOTOS_KEY, GEOMETRY_KEY, INHERITED_KEY))
        return cls(photos=None if photos is None else PhotosDecision.from_json(photos),
                   geometry=None if geometry is None else GeometryChoice.from_json(geometry),
                   inherited=None if inherited is None else InheritedCalibration.from_json(inherited))

    @classmethod
    def read(cls, path: Path) -> AlignDecisions:
        """The records in the align.json at `path`."""
        return cls.from_json(json.loads(Path(path).read_text()))


@dataclass(frozen=True)
class AlignStageResult:
    """An alignment as the align stage keeps it: mvgeo's result and the stage's decisions about it.

    Attributes:
        alignment: the cameras, poses, points and `AlignStats` (`mvgeo.align.align_images`, or a previous
            round's handed over).
        decisions: the stage's records about `alignment`, written into its align.json.
    """

    alignment: AlignResult
    decisions: AlignDecisions = AlignDecisions()

    def align_json(self) -> dict[str, Any]:
        """The align.json document: `alignment.stats`' fields and the decisions' keys beside them."""
        return self.alignment.stats.to_json(extra_keys=self.decisions.to_json())

    def write(self, out: Path) -> Path:
        """`out/sparse/0/*.bin`, `out/points.ply` and `out/align.json` (with the decisions), atomically."""
        return write_align_result(out, self.alignment, extra_keys=self.decisions.to_json())
