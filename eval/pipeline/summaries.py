"""Typed stage summaries: what each product stage returns, records in its stage record and report.json.

A stage function returns a JSON-able mapping (`eval.pipeline.stage.StageFn`); the stage runner records it
and hands it back, from the record when the stage is skipped (`StageResult.summary`). The stages build
these types and return their ``to_json()``; the readers in other modules (`eval.pipeline.quality`,
`eval.pipeline.report`, `eval.pipeline.run`) parse the recorded mapping with ``from_json`` and read fields.

Each type's JSON is the summary as the stage records hold it, key for key, so existing run folders read
back. Each ``from_json`` also reads the summaries of the stage functions that stand in for a product stage (the
evaluation's classical denoisers and ground-truth alignment in `eval.baselines`, the small stages tests
pass): a key the JSON lacks is None (or empty) here, and ``to_json`` leaves a None field out, so
``from_json(x).to_json() == x`` for every summary the stages write. Keys no field knows are not read.

| stage               | type             | readers                                          |
|---------------------|------------------|--------------------------------------------------|
| inputs              | `InputsSummary`  | report (working sizes)                           |
| denoise             | `DenoiseSummary` | quality (training, objective, noise levels)      |
| align               | `AlignSummary`   | quality (which photos were aligned, why)         |
| fuse                | `FuseSummary`    | tests                                            |
| splat               | `SplatSummary`   | quality (Gaussians, optimisation seconds)        |
| select              | `SelectSummary`  | report (selected views)                          |
| refine              | `RefineSummary`  | quality (fine-tuning loss), run (kept previous?) |
| export              | `ExportSummary`  | report (Gaussians)                               |

Align.json's own records (which photos round 1 aligned, a round's geometry choice) are typed in
`eval.pipeline.align_decisions`; the align summary holds them as those types. This module imports neither
torch nor the component packages' network code: report writing reads it.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoise.detail import NoisyDetail  # numpy and cv2 only
from denoise.training_restart import TrainingRestart
from eval.pipeline.align_decisions import GeometryChoice, PhotosDecision

if TYPE_CHECKING:
    from denoise.round2 import Round2Report

__all__ = ["AlignSummary", "DenoiseSummary", "ExportSummary", "FuseSummary", "HistoryEnds",
           "InputsSummary", "NoisyDetailRecord", "PhotoNoise", "RecordedGeometryChoice", "RefineSummary",
           "SelectSummary", "SelectionFile", "SplatSummary", "WorkingSize", "history_ends"]


def _opt[T](data: Mapping[str, Any], key: str, parse: Callable[[Any], T]) -> T | None:
    """`parse(data[key])`, or None where `data` lacks `key` or holds null there."""
    value = data.get(key)
    return None if value is None else parse(value)


def _str_list(value: Any) -> list[str]:
    return [str(v) for v in value]


def _float_map(value: Any) -> dict[str, float]:
    return {str(k): float(v) for k, v in value.items()}


def _without_none(items: dict[str, object]) -> dict[str, object]:
    """`items` in order, the None values left out (a field the JSON lacked stays absent)."""
    return {k: v for k, v in items.items() if v is not None}


# ----------------------------------------------------------------- shared records
@dataclass(frozen=True)
class HistoryEnds:
    """One training curve's ends: its first and last value and how many values it holds.

    Attributes:
        first, last: the curve's first and last values (floats, whatever the curve's type).
        count: number of values in the curve.
    """

    first: float
    last: float
    count: int

    def to_json(self) -> dict[str, object]:
        return {"first": self.first, "last": self.last, "count": self.count}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> HistoryEnds:
        """The record `to_json` wrote.

        Raises:
            KeyError: a missing ``first``, ``last`` or ``count``.
        """
        return cls(float(data["first"]), float(data["last"]), int(data["count"]))


def history_ends(history: object) -> dict[str, HistoryEnds]:
    """Curve name -> `HistoryEnds` of a training history: a list of losses (named "loss"), or a mapping of
    name -> list (`splat.train.TrainHistory` as a dict). Empty curves and curves whose last value is not a
    number are left out."""
    if isinstance(history, list | tuple) and history and isinstance(history[-1], int | float):
        history = {"loss": history}
    out: dict[str, HistoryEnds] = {}
    if isinstance(history, Mapping):
        for k, v in history.items():
            if isinstance(v, list | tuple) and v and isinstance(v[-1], int | float):
                out[str(k)] = HistoryEnds(float(v[0]), float(v[-1]), len(v))
    return out


def _train_to_json(train: Mapping[str, HistoryEnds]) -> dict[str, object]:
    return {k: v.to_json() for k, v in train.items()}


def _train_from_json(value: Any) -> dict[str, HistoryEnds]:
    """A summary's ``train`` record; entries that are not records (none the stages write) are not read."""
    if not isinstance(value, Mapping):
        return {}
    return {str(k): HistoryEnds.from_json(v) for k, v in value.items() if isinstance(v, Mapping)}


@dataclass(frozen=True)
class PhotoNoise:
    """The denoise stage's record of its photos' noise, as the default denoiser estimates it
    (`eval.pipeline.quality.noise_levels`).

    Attributes:
        noise_std_255: view -> noise std, /255 (the median of the per-pixel map for `signal_dependent` views).
        signal_dependent: the views whose noise grows with the intensity (e.g. shot noise), in order.
    """

    noise_std_255: dict[str, float] = field(default_factory=dict)
    signal_dependent: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, object]:
        return {"noise_std_255": dict(self.noise_std_255), "signal_dependent": list(self.signal_dependent)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> PhotoNoise:
        """The record `to_json` wrote (a missing key: empty)."""
        return cls(_float_map(data.get("noise_std_255", {})), _str_list(data.get("signal_dependent", [])))


# ----------------------------------------------------------------- inputs
@dataclass(frozen=True)
class WorkingSize:
    """One photo's entry in the inputs stage's ``sizes`` (and in `sizes.json`, `eval.pipeline.inputs`).

    Attributes:
        input_wh: the photo's (width, height), px.
        working_wh: its working image's (width, height), px.
        focal_35mm: the photo's EXIF 35 mm-equivalent focal length, mm; None: not in its EXIF.
        turned: quarter turns counter-clockwise from the photo to its working image (0 or 1).
        file: the photo's file name in the input folder (``IMG_0001.JPG``; the working image is
            ``IMG_0001.png``), which names it in `cameras/input/`; None: not recorded (an older record).
    """

    input_wh: tuple[int, int]
    working_wh: tuple[int, int]
    focal_35mm: float | None = None
    turned: int = 0
    file: str | None = None

    def to_json(self) -> dict[str, object]:
        """``{"input": [W, H], "working": [W, H], "focal_35mm": ...}``, plus ``"turned": 1`` for a turned photo
        and ``"file"`` where recorded."""
        return {"input": list(self.input_wh), "working": list(self.working_wh), "focal_35mm": self.focal_35mm,
                **({"turned": self.turned} if self.turned else {}), **({"file": self.file} if self.file else {})}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> WorkingSize:
        """The record `to_json` wrote.

        Raises:
            KeyError: a missing ``input`` or ``working``.
        """
        w, h = data["input"]
        ww, wh = data["working"]
        return cls((int(w), int(h)), (int(ww), int(wh)), _opt(data, "focal_35mm", float), int(data.get("turned", 0)),
                   _opt(data, "file", str))


@dataclass(frozen=True)
class InputsSummary:
    """The inputs stage's summary (`eval.pipeline.inputs.prepare_inputs`).

    Attributes:
        max_size: the working images' longest side limit, px; None: the input size.
        sizes: view -> its photo's and working image's sizes.
        resized: the views whose working image differs in size from the photo (sorted).
        turned: the views turned a quarter to the others' orientation (sorted); None where none was.
    """

    max_size: int | None
    sizes: dict[str, WorkingSize] = field(default_factory=dict)
    resized: list[str] = field(default_factory=list)
    turned: list[str] | None = None

    def to_json(self) -> dict[str, object]:
        return {"max_size": self.max_size, "sizes": {k: v.to_json() for k, v in self.sizes.items()},
                "resized": list(self.resized), **({"turned": list(self.turned)} if self.turned is not None else {})}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> InputsSummary:
        return cls(max_size=_opt(data, "max_size", int),
                   sizes={str(k): WorkingSize.from_json(v) for k, v in data.get("sizes", {}).items()},
                   resized=_str_list(data.get("resized", [])), turned=_opt(data, "turned", _str_list))


# ----------------------------------------------------------------- denoise, refine
@dataclass(frozen=True)
class DenoiseSummary:
    """Round 1's denoise stage summary: the product's (`eval.pipeline.stages.denoise`) or a classical
    denoiser's (`eval.baselines`: `denoiser`, `sigma_est` only). None: not recorded.

    Attributes:
        views: the denoised views' stems, in order.
        train: the network's training curve(s) (`history_ends`; "loss").
        objective: the self-supervised objective `choose_objective` picked; None: the preset's.
        dark_clipped_fraction: the photos' dark and clipped area fraction that chose it.
        training_restarts: the trainings the divergence guard abandoned (empty: none, and not written).
        pd_stride: the pixel-shuffle stride the photos were denoised at (1: none).
        noise_level_by_stride_255: stride -> the noise level read on the sub-images at that stride, /255
            (`denoise.pixel_shuffle.NoiseLevels`); None where none was read.
        noise_level_luma_255: where the photos' noise is chroma-subsampled (a JPEG's), the level their luma
            reads, /255 (`denoise.pixel_shuffle.NoiseLevels.luma_level`); None otherwise.
        noise_level_luma_hint_255: where no noise was found but the photos look like a camera's JPEGs, the level
            their stride-2 sub-images' luma reads, /255 (`NoiseLevels.luma_hint_level`; the report suggests
            `--pd-stride 2 --noise-model luma`); None otherwise, and where a noise model was given.
        passed_through: True where every photo's noise level read under `DenoiseStageSettings.
            pass_clean_below_255`: the photos were written as they are, no network trained; None otherwise.
        noise: each photo's noise level (the report's).
        denoiser: a classical denoiser's name (`eval.baselines`).
        sigma_est: a classical denoiser's noise estimate per view, [0, 1] units.
    """

    views: list[str] | None = None
    train: dict[str, HistoryEnds] | None = None
    objective: str | None = None
    dark_clipped_fraction: float | None = None
    training_restarts: list[TrainingRestart] = field(default_factory=list)
    pd_stride: int | None = None
    noise_level_by_stride_255: dict[str, float] | None = None
    noise_level_luma_255: float | None = None
    noise_level_luma_hint_255: float | None = None
    passed_through: bool | None = None
    noise: PhotoNoise | None = None
    denoiser: str | None = None
    sigma_est: dict[str, float] | None = None

    @property
    def loss(self) -> HistoryEnds | None:
        """The training loss curve's ends; None where no training was recorded."""
        return None if self.train is None else self.train.get("loss")

    def to_json(self) -> dict[str, object]:
        restarts = [r.to_json() for r in self.training_restarts] or None
        return _without_none({
            "views": None if self.views is None else list(self.views),
            "train": None if self.train is None else _train_to_json(self.train),
            "objective": self.objective, "dark_clipped_fraction": self.dark_clipped_fraction,
            "training_restarts": restarts, "pd_stride": self.pd_stride,
            "noise_level_by_stride_255": self.noise_level_by_stride_255,
            "noise_level_luma_255": self.noise_level_luma_255,
            "noise_level_luma_hint_255": self.noise_level_luma_hint_255,
            "passed_through": self.passed_through,
            **(self.noise.to_json() if self.noise is not None else {}),
            "denoiser": self.denoiser, "sigma_est": self.sigma_est})

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> DenoiseSummary:
        has_noise = "noise_std_255" in data or "signal_dependent" in data
        return cls(views=_opt(data, "views", _str_list), train=_opt(data, "train", _train_from_json),
                   objective=_opt(data, "objective", str),
                   dark_clipped_fraction=_opt(data, "dark_clipped_fraction", float),
                   training_restarts=[TrainingRestart.from_json(r) for r in data.get("training_restarts", [])],
                   pd_stride=_opt(data, "pd_stride", int),
                   noise_level_by_stride_255=_opt(data, "noise_level_by_stride_255", _float_map),
                   noise_level_luma_255=_opt(data, "noise_level_luma_255", float),
                   noise_level_luma_hint_255=_opt(data, "noise_level_luma_hint_255", float),
                   passed_through=_opt(data, "passed_through", bool),
                   noise=PhotoNoise.from_json(data) if has_noise else None,
                   denoiser=_opt(data, "denoiser", str), sigma_est=_opt(data, "sigma_est", _float_map))


@dataclass(frozen=True)
class RefineSummary:
    """A round >= 2 refine stage's summary (`eval.pipeline.stages.refine`). None: not recorded.

    Attributes:
        views: the selected views it fine-tuned on and denoised, in order.
        train: the fine-tuning's curve(s) (`history_ends`; "loss": round 1's losses, then the fine-tuning's).
        pd_stride: the pixel-shuffle stride the photos were denoised at (1: none).
        round2: `denoise.round2.Round2Report.to_json()` (kept as JSON: parsing it loads torch; see
            `round2_report`).
    """

    views: list[str] | None = None
    train: dict[str, HistoryEnds] | None = None
    pd_stride: int | None = None
    round2: dict[str, object] | None = None

    @property
    def loss(self) -> HistoryEnds | None:
        """The loss curve's ends; None where no training was recorded."""
        return None if self.train is None else self.train.get("loss")

    def round2_report(self) -> Round2Report | None:
        """The `denoise.round2.Round2Report` recorded (imports torch); None where none was."""
        from denoise.round2 import Round2Report

        return None if self.round2 is None else Round2Report.from_json(self.round2)

    def kept_previous(self) -> tuple[bool, str]:
        """(True when the blind-spot-loss guard kept the previous network, why in words); (False, "")
        without a round-2 report."""
        report = self.round2_report()
        if report is None:
            return False, ""
        return report.reverted, report.kept_previous_because()

    def to_json(self) -> dict[str, object]:
        return _without_none({"views": None if self.views is None else list(self.views),
                              "train": None if self.train is None else _train_to_json(self.train),
                              "pd_stride": self.pd_stride, "round2": self.round2})

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> RefineSummary:
        round2 = data.get("round2")
        return cls(views=_opt(data, "views", _str_list), train=_opt(data, "train", _train_from_json),
                   pd_stride=_opt(data, "pd_stride", int),
                   round2=dict(round2) if isinstance(round2, Mapping) else None)


# ----------------------------------------------------------------- align
@dataclass(frozen=True)
class AlignSummary:
    """The align stage's summary: the product's (`eval.pipeline.align_stage.align`) or the ground-truth
    cameras' (`eval.baselines.gt_align`: `poses`, `points_from`). None: not recorded.

    Attributes:
        registered: views registered.
        points: points in `points.npz` (the splat's start).
        stats: align.json's `AlignStats` fields as `AlignStats.to_json` writes them (readers read align.json
            with `AlignStats.read`; the copy here is for the record and report.json).
        geometry: rounds >= 2: this round's poses or the previous round's (align.json's record of it).
        photos: round 1: which photos were aligned, and why (align.json's record of it).
        poses, points_from: `gt_align`'s cameras and initial points, in words.
    """

    registered: int | None = None
    points: int | None = None
    stats: dict[str, object] | None = None
    geometry: GeometryChoice | None = None
    photos: PhotosDecision | None = None
    poses: str | None = None
    points_from: str | None = None

    def to_json(self) -> dict[str, object]:
        return _without_none({"registered": self.registered, "points": self.points, "stats": self.stats,
                              "geometry": None if self.geometry is None else self.geometry.to_json(),
                              "photos": None if self.photos is None else self.photos.to_json(),
                              "poses": self.poses, "points_from": self.points_from})

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> AlignSummary:
        return cls(registered=_opt(data, "registered", int), points=_opt(data, "points", int),
                   stats=_opt(data, "stats", dict), geometry=_opt(data, "geometry", GeometryChoice.from_json),
                   photos=_opt(data, "photos", PhotosDecision.from_json),
                   poses=_opt(data, "poses", str), points_from=_opt(data, "points_from", str))


# ----------------------------------------------------------------- fuse, splat
@dataclass(frozen=True)
class RecordedGeometryChoice:
    """The align stage's rounds >= 2 decision (`GeometryChoice`) as the fuse stage records it: whether and why.

    Attributes:
        used_previous: True: the previous round's cameras were kept; None: not recorded.
        reason: why, in words.
    """

    used_previous: bool | None
    reason: str | None

    def to_json(self) -> dict[str, object]:
        return {"used_previous": self.used_previous, "reason": self.reason}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> RecordedGeometryChoice:
        return cls(_opt(data, "used_previous", bool), _opt(data, "reason", str))


@dataclass(frozen=True)
class FuseSummary:
    """The fuse stage's summary (`eval.pipeline.fuse_stage.fuse`). None: not recorded.

    Attributes:
        views: the views fused, in the alignment's order.
        weight: the noisy-photo splat render's weight (`FUSE_WEIGHT`).
        noisy_splat: "reused" (the previous round's renders) or "trained".
        noisy_splat_reason: why, in words.
        align_geometry: the alignment's rounds >= 2 decision, where it made one.
        timings_s: the noisy-photo splat's seconds per phase (`splat.train.TrainResult.timings_s`); None
            where it was reused.
    """

    views: list[str] | None = None
    weight: float | None = None
    noisy_splat: str | None = None
    noisy_splat_reason: str | None = None
    align_geometry: RecordedGeometryChoice | None = None
    timings_s: dict[str, float] | None = None

    def to_json(self) -> dict[str, object]:
        return _without_none({
            "views": None if self.views is None else list(self.views), "weight": self.weight,
            "noisy_splat": self.noisy_splat, "noisy_splat_reason": self.noisy_splat_reason,
            "align_geometry": None if self.align_geometry is None else self.align_geometry.to_json(),
            "timings_s": None if self.timings_s is None else dict(self.timings_s)})

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> FuseSummary:
        return cls(views=_opt(data, "views", _str_list), weight=_opt(data, "weight", float),
                   noisy_splat=_opt(data, "noisy_splat", str), noisy_splat_reason=_opt(data, "noisy_splat_reason", str),
                   align_geometry=_opt(data, "align_geometry", RecordedGeometryChoice.from_json),
                   timings_s=_opt(data, "timings_s", _float_map))


@dataclass(frozen=True)
class NoisyDetailRecord:
    """The splat stage's noisy-detail targets (`PipelineConfig.splat.noisy_detail`).

    Attributes:
        detail: the setting.
        weights: view -> the weight its target took (`denoise.detail.noisy_detail_weight`).
    """

    detail: NoisyDetail
    weights: dict[str, float]

    def to_json(self) -> dict[str, object]:
        """The setting's fields, then ``"weights"``."""
        return {**dataclasses.asdict(self.detail), "weights": dict(self.weights)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> NoisyDetailRecord:
        names = {f.name for f in dataclasses.fields(NoisyDetail)}
        return cls(NoisyDetail(**{k: v for k, v in data.items() if k in names}), _float_map(data.get("weights", {})))


@dataclass(frozen=True)
class SplatSummary:
    """The splat stage's summary (`eval.pipeline.stages.splat`). None: not recorded.

    Attributes:
        views: the views trained on, in the alignment's order.
        train: the training curves' ends (`splat.train.TrainHistory`'s: "loss", "num_gaussians", ...).
        noisy_detail: the noisy-detail targets, where they were on.
        timings_s: seconds per phase (`splat.train.TrainResult.timings_s`: "setup", "optimize", "total", ...).
    """

    views: list[str] | None = None
    train: dict[str, HistoryEnds] | None = None
    noisy_detail: NoisyDetailRecord | None = None
    timings_s: dict[str, float] | None = None

    @property
    def num_gaussians(self) -> int | None:
        """Gaussians at the end of the training; None where not recorded."""
        ends = None if self.train is None else self.train.get("num_gaussians")
        return None if ends is None else int(ends.last)

    @property
    def optimize_s(self) -> float | None:
        """Seconds of the optimisation ("optimize" in `timings_s`); None where not recorded."""
        return None if self.timings_s is None else self.timings_s.get("optimize")

    def to_json(self) -> dict[str, object]:
        return _without_none({"views": None if self.views is None else list(self.views),
                              "train": None if self.train is None else _train_to_json(self.train),
                              "noisy_detail": None if self.noisy_detail is None else self.noisy_detail.to_json(),
                              "timings_s": None if self.timings_s is None else dict(self.timings_s)})

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> SplatSummary:
        return cls(views=_opt(data, "views", _str_list), train=_opt(data, "train", _train_from_json),
                   noisy_detail=_opt(data, "noisy_detail", NoisyDetailRecord.from_json),
                   timings_s=_opt(data, "timings_s", _float_map))


# ----------------------------------------------------------------- select, export
@dataclass(frozen=True)
class SelectSummary:
    """The select stage's summary (`eval.pipeline.stages.select`; selection.json holds the details).

    Attributes:
        selected: the views kept for the round, in order.
        method: "kmeans+laplacian", "all" or "all (N <= K)"; None: not recorded.
    """

    selected: list[str] = field(default_factory=list)
    method: str | None = None

    def to_json(self) -> dict[str, object]:
        return _without_none({"selected": list(self.selected), "method": self.method})

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> SelectSummary:
        return cls(_str_list(data.get("selected", [])), _opt(data, "method", str))


@dataclass(frozen=True)
class SelectionFile:
    """selection.json, the select stage's output that the refine stage reads (`eval.pipeline.stages.select`).

    Attributes:
        names: the views kept for the round, in order (file stems).
        method: "kmeans+laplacian", "all" (selection off) or "all (N <= K)".
        cluster_of: with "kmeans+laplacian", view -> its pose cluster.
        laplacian_var: with "kmeans+laplacian", view -> the variance of its Laplacian (the sharpness kept).
    """

    names: list[str]
    method: str
    cluster_of: dict[str, int] | None = None
    laplacian_var: dict[str, float] | None = None

    def to_json(self) -> dict[str, object]:
        return _without_none({"names": list(self.names), "method": self.method,
                              "cluster_of": None if self.cluster_of is None else dict(self.cluster_of),
                              "laplacian_var": None if self.laplacian_var is None else dict(self.laplacian_var)})

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> SelectionFile:
        return cls(_str_list(data.get("names", [])), str(data.get("method", "")),
                   _opt(data, "cluster_of", lambda d: {str(k): int(v) for k, v in d.items()}),
                   _opt(data, "laplacian_var", _float_map))

    def write(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")

    @classmethod
    def read(cls, path: Path) -> SelectionFile:
        return cls.from_json(json.loads(Path(path).read_text()))


@dataclass(frozen=True)
class ExportSummary:
    """The export stage's summary (`eval.pipeline.publish.export`). None: not recorded.

    Attributes:
        num_gaussians: Gaussians in `scene.splat`.
        splat_bytes: its size in bytes.
        working_size, input_size: the distinct camera sizes ("WxH", sorted) in `cameras/working/` and
            `cameras/input/`.
    """

    num_gaussians: int | None = None
    splat_bytes: int | None = None
    working_size: list[str] | None = None
    input_size: list[str] | None = None

    def to_json(self) -> dict[str, object]:
        return _without_none(dataclasses.asdict(self))

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ExportSummary:
        return cls(num_gaussians=_opt(data, "num_gaussians", int), splat_bytes=_opt(data, "splat_bytes", int),
                   working_size=_opt(data, "working_size", _str_list), input_size=_opt(data, "input_size", _str_list))
