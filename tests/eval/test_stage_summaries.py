"""`eval.pipeline.summaries`: the typed stage summaries read the JSON the stages write, and write it back
unchanged, key order included (report.json copies a fresh summary as the stage returned it)."""

from __future__ import annotations

import json

import pytest

from denoise.detail import NoisyDetail
from denoise.training_restart import TrainingRestart
from eval.pipeline.align_decisions import GeometryChoice, PerPhotos, PhotosComparison, PhotosDecision
from eval.pipeline.summaries import (
    AlignSummary,
    DenoiseSummary,
    ExportSummary,
    FuseSummary,
    HistoryEnds,
    InputsSummary,
    NoisyDetailRecord,
    PhotoNoise,
    RecordedGeometryChoice,
    RefineSummary,
    SelectionFile,
    SelectSummary,
    SplatSummary,
    WorkingSize,
    history_ends,
)

# ----------------------------------------------------------------- summaries as the stages write them
# Literal copies of what each stage function returns (the keys, their order and the JSON types of the
# values), so that a change to the types that would change the written JSON, or fail to read a run
# folder's records, fails here.
DENOISE = {
    "views": ["view_000", "view_001"],
    "train": {"loss": {"first": 1.25, "last": 0.5, "count": 400}},
    "objective": "neighbor2neighbor", "dark_clipped_fraction": 0.6132,
    "training_restarts": [{"step": 37, "lr": 0.003}, {"step": 52, "lr": 0.0015}],
    "pd_stride": 2, "noise_level_by_stride_255": {"1": 4.1, "2": 12.62, "3": 12.8}, "noise_level_luma_255": 24.3,
    "noise_std_255": {"view_000": 24.8, "view_001": 25.3}, "signal_dependent": ["view_001"],
}
DENOISE_PLAIN = {  # the preset's objective, no restart, stride 1 set by hand (no levels read)
    "views": ["a"], "train": {"loss": {"first": 0.9, "last": 0.4, "count": 8}}, "pd_stride": 1,
    "noise_std_255": {"a": 10.0}, "signal_dependent": [],
}
CLASSICAL_DENOISE = [{"denoiser": "none"}, {"denoiser": "skimage.denoise_nl_means", "sigma_est": {"a": 0.098}},
                     {"denoiser": "oracle (clean photos)"}]
REFINE = {
    "views": ["view_000", "view_002", "view_005"],
    "train": {"loss": {"first": 1.25, "last": 0.48, "count": 411}}, "pd_stride": 1,
    "round2": {"render_weight": [0.7, 0.8, 0.9], "loss_before": 0.0123, "loss_after": 0.0121,
               "loss_gain_se": 1e-05, "reverted": False},
}
GEOMETRY = {"used_previous": True, "reason": "this round registered fewer of the views than the previous round",
            "views": ["a.png", "b.png"], "previous_registered": 2, "current_registered": 1,
            "previous_centre_std": 0.004, "current_centre_std": None, "current_error": None}
ALIGN_STATS = {"n_images": 2, "n_registered": 2, "focal_px": {"a.png": 512.0, "b.png": 512.0}}
ALIGN = [
    {"registered": 2, "points": 5000, "stats": ALIGN_STATS,
     "photos": {"aligned": "denoised", "registered": {"denoised": 2, "noisy": 2},
                "centre_std_over_spacing": {"denoised": 0.006, "noisy": None},
                "reason": "the denoised photos' alignment: its camera centres are better determined"}},
    {"registered": 2, "points": 5000, "stats": ALIGN_STATS, "photos": {"aligned": "noisy"}},
    {"registered": 2, "points": 5000, "stats": ALIGN_STATS,
     "photos": {"aligned": "denoised", "noisy_refused": "3 views' pairs contradicted"}},
    {"registered": 2, "points": 5000, "stats": ALIGN_STATS,
     "photos": {"aligned": "noisy", "denoised_refused": "disconnected views"}},
    {"registered": 2, "points": 5000, "stats": ALIGN_STATS, "geometry": GEOMETRY},  # a round >= 2
    {"registered": 3, "points": 700, "poses": "ground truth", "points_from": "ground truth"},  # gt_align
]
FUSE = [
    {"views": ["a", "b"], "weight": 0.5, "noisy_splat": "trained",
     "noisy_splat_reason": "round 1 has no previous round",
     "timings_s": {"setup": 0.5, "optimize": 12.25, "total": 12.75}},
    {"views": ["a"], "weight": 0.5, "noisy_splat": "reused",
     "noisy_splat_reason": "the same noisy photos, cameras, poses and points as the previous round's splat",
     "align_geometry": {"used_previous": False, "reason": "this round's alignment is better determined"}},
]
SPLAT = [
    {"views": ["a", "b"],
     "train": {"iteration": {"first": 0.0, "last": 300.0, "count": 11},
               "loss": {"first": 0.3, "last": 0.05, "count": 11},
               "num_gaussians": {"first": 900.0, "last": 1234.0, "count": 11}},
     "timings_s": {"setup": 0.5, "optimize": 42.0, "optimize/render": 20.0, "total": 42.5}},
    {"views": ["a"], "train": {"loss": {"first": 0.3, "last": 0.05, "count": 2}},
     "noisy_detail": {"weight": 0.5, "sigma_px": 1.0, "reference_std": 0.09803921568627451, "skip_dark_clipped": True,
                      "weights": {"a": 0.41}},
     "timings_s": {"optimize": 1.0}},
]
SELECT = [{"selected": ["a", "c"], "method": "kmeans+laplacian"}, {"selected": ["a", "b"], "method": "all (N <= K)"}]
SELECTION_FILE = [{"names": ["a", "c"], "method": "kmeans+laplacian", "cluster_of": {"a": 0, "b": 1, "c": 1},
                   "laplacian_var": {"a": 0.002, "b": 0.001, "c": 0.003}},
                  {"names": ["a", "b"], "method": "all"}]
INPUTS = [
    {"max_size": 512, "sizes": {"a": {"input": [1024, 768], "working": [512, 384], "focal_35mm": 28.0},
                                "b": {"input": [768, 1024], "working": [512, 384], "focal_35mm": None, "turned": 1,
                                      "file": "b.JPG"}},
     "resized": ["a", "b"], "turned": ["b"]},
    {"max_size": None, "sizes": {"a": {"input": [64, 48], "working": [64, 48], "focal_35mm": None}}, "resized": []},
]
EXPORT = {"num_gaussians": 1234, "splat_bytes": 39488, "working_size": ["512x384"], "input_size": ["1024x768"]}

CASES = ([(DenoiseSummary, s) for s in (DENOISE, DENOISE_PLAIN, *CLASSICAL_DENOISE)] + [(RefineSummary, REFINE)]
         + [(AlignSummary, s) for s in ALIGN] + [(FuseSummary, s) for s in FUSE]
         + [(SplatSummary, s) for s in SPLAT] + [(SelectSummary, s) for s in SELECT]
         + [(SelectionFile, s) for s in SELECTION_FILE]
         + [(InputsSummary, s) for s in INPUTS] + [(ExportSummary, EXPORT)])


@pytest.mark.parametrize(("cls", "written"), CASES, ids=lambda x: x.__name__ if isinstance(x, type) else "")
def test_a_summary_as_the_stage_writes_it_reads_and_writes_back_byte_for_byte(cls, written):
    text = json.dumps(written)
    assert json.dumps(cls.from_json(json.loads(text)).to_json()) == text
    # From the stage record, which sorts the keys: the same values (the order is the type's).
    recorded = json.loads(json.dumps({"summary": written}, indent=2, sort_keys=True))["summary"]
    assert cls.from_json(recorded).to_json() == written


def test_the_readers_fields_hold_what_the_summaries_record():
    d = DenoiseSummary.from_json(DENOISE)
    assert d.loss == HistoryEnds(1.25, 0.5, 400) and d.objective == "neighbor2neighbor"
    assert d.training_restarts == [TrainingRestart(37, 0.003), TrainingRestart(52, 0.0015)]
    assert d.noise == PhotoNoise({"view_000": 24.8, "view_001": 25.3}, ["view_001"])
    assert (d.pd_stride, d.noise_level_by_stride_255) == (2, {"1": 4.1, "2": 12.62, "3": 12.8})
    assert d.noise_level_luma_255 == 24.3
    nlm = DenoiseSummary.from_json(CLASSICAL_DENOISE[1])
    assert nlm.loss is None and nlm.noise is None and nlm.sigma_est == {"a": 0.098} and nlm.training_restarts == []
    r = RefineSummary.from_json(REFINE)
    assert r.loss == HistoryEnds(1.25, 0.48, 411) and r.kept_previous() == (False, "")
    reverted = RefineSummary.from_json({**REFINE, "round2": {**REFINE["round2"], "reverted": True}})
    kept, why = reverted.kept_previous()
    assert kept and "previous network" in why
    assert RefineSummary.from_json({}).kept_previous() == (False, "")  # a test stage's summary: no report
    better_of = AlignSummary.from_json(ALIGN[0])
    assert better_of.photos.aligned == "denoised" and better_of.photos.comparison.registered == PerPhotos(2, 2)
    assert AlignSummary.from_json(ALIGN[4]).geometry.current_registered == 1
    s = SplatSummary.from_json(SPLAT[0])
    assert (s.num_gaussians, s.optimize_s) == (1234, 42.0)
    assert SplatSummary.from_json(SPLAT[1]).noisy_detail.detail == NoisyDetail(0.5)
    assert SplatSummary.from_json({}).num_gaussians is None and SplatSummary.from_json({}).optimize_s is None
    sizes = InputsSummary.from_json(INPUTS[0]).sizes
    assert sizes["b"] == WorkingSize((768, 1024), (512, 384), None, turned=1, file="b.JPG")
    assert sizes["a"].focal_35mm == 28.0 and sizes["a"].file is None
    assert SelectSummary.from_json(SELECT[0]).selected == ["a", "c"]
    chosen = SelectionFile.from_json(SELECTION_FILE[0])
    assert chosen.names == ["a", "c"] and chosen.cluster_of["c"] == 1 and chosen.laplacian_var["b"] == 0.001
    assert SelectionFile.from_json(SELECTION_FILE[1]).cluster_of is None
    assert ExportSummary.from_json(EXPORT).num_gaussians == 1234


ROUND_TRIPS = [
    DenoiseSummary(views=["a"], train={"loss": HistoryEnds(1.0, 0.5, 3)}, objective="r2r", dark_clipped_fraction=0.1,
                   training_restarts=[TrainingRestart(5, 0.01)], pd_stride=2, noise_level_by_stride_255={"1": 3.0},
                   noise=PhotoNoise({"a": 12.0}, ["a"])),
    DenoiseSummary(denoiser="skimage.denoise_nl_means", sigma_est={"a": 0.1}),
    DenoiseSummary(),
    RefineSummary(views=["a"], train={"loss": HistoryEnds(1.0, 0.4, 9)}, pd_stride=1, round2={"reverted": True}),
    AlignSummary(registered=2, points=10, stats={"n_images": 2}, geometry=GeometryChoice.from_json(GEOMETRY),
                 photos=PhotosDecision("denoised", comparison=PhotosComparison(PerPhotos(2, 1), PerPhotos(0.1, None),
                                                                               "it registers more of the views"))),
    AlignSummary(registered=2, points=10, photos=PhotosDecision("noisy", denoised_refused="refused")),
    FuseSummary(views=["a"], weight=0.5, noisy_splat="reused", noisy_splat_reason="same",
                align_geometry=RecordedGeometryChoice(True, "fewer views"), timings_s={"optimize": 1.5}),
    SplatSummary(views=["a"], train={"num_gaussians": HistoryEnds(10.0, 20.0, 2)},
                 noisy_detail=NoisyDetailRecord(NoisyDetail(0.25, 2.0, None, False), {"a": 0.25}),
                 timings_s={"optimize": 3.0}),
    SelectSummary(["a"], "all"),
    InputsSummary(512, {"a": WorkingSize((100, 80), (50, 40), 35.0), "b": WorkingSize((80, 100), (50, 40), None, 1)},
                  ["a", "b"], ["b"]),
    InputsSummary(None),
    ExportSummary(1, 32, ["4x3"], ["8x6"]),
    HistoryEnds(0.5, 0.25, 7),
    PhotoNoise({"a": 1.0}, []),
    WorkingSize((3, 2), (3, 2)),
    RecordedGeometryChoice(None, None),
    NoisyDetailRecord(NoisyDetail(), {}),
]


@pytest.mark.parametrize("value", ROUND_TRIPS, ids=lambda v: type(v).__name__)
def test_every_type_survives_a_json_round_trip(value):
    text = json.dumps(value.to_json())
    assert type(value).from_json(json.loads(text)) == value


def test_history_ends_records_each_numeric_curve_as_the_stages_did():
    assert history_ends([3, 2.5, 1.0]) == {"loss": HistoryEnds(3.0, 1.0, 3)}  # a list of losses is "loss"
    assert history_ends({"loss": [0.3, 0.1], "num_gaussians": [10, 12, 14], "empty": [], "names": ["a"]}) == {
        "loss": HistoryEnds(0.3, 0.1, 2), "num_gaussians": HistoryEnds(10.0, 14.0, 3)}
    assert history_ends([]) == {} and history_ends(None) == {}
    # The JSON holds floats whatever the curve's type (`num_gaussians` is a list of ints).
    assert json.dumps(history_ends({"n": [1, 2]})["n"].to_json()) == '{"first": 1.0, "last": 2.0, "count": 2}'
