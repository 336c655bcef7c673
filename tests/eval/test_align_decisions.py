"""`eval.pipeline.align_decisions`: the align stage's typed records, their JSON round trips, and align.json
documents written before the records were typed (literal dicts under the same keys) reading back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from eval.pipeline.align_decisions import (
    GEOMETRY_KEY,
    INHERITED_KEY,
    PHOTOS_KEY,
    AlignDecisions,
    AlignStageResult,
    FocalEstimate,
    GeometryChoice,
    InheritedCalibration,
    PerPhotos,
    PhotosComparison,
    PhotosDecision,
)
from mvgeo.align.result import AlignResult
from mvgeo.align.stats import AlignStats
from mvgeo.camera import Camera
from mvgeo.sparse_model import PosedImage, SparseModel
from tests.common.align_stats import align_stats, bundle_stats

COMPARISON = PhotosComparison(registered=PerPhotos(denoised=8, noisy=7),
                              centre_std_over_spacing=PerPhotos(denoised=0.0061, noisy=None),
                              reason="the denoised photos' alignment: it registers more of the views")
GEOMETRY = GeometryChoice(used_previous=True, reason="this round registered fewer of the views",
                          views=("a.png", "b.png", "c.png"), previous_registered=3, current_registered=2,
                          previous_centre_std=0.012, current_centre_std=None, current_error="degenerate")
INHERITED = InheritedCalibration(focal_px=212.0, focal_log_std=0.02, mode="auto", used=True,
                                 estimate_discarded=FocalEstimate(focal_px=168.0, focal_log_std=0.046))

# The records as the align stage wrote them into align.json before they were typed (same keys, same values).
LEGACY_PHOTOS = [
    ({"aligned": "denoised"}, PhotosDecision("denoised")),
    ({"aligned": "noisy"}, PhotosDecision("noisy")),
    ({"aligned": "denoised", "noisy_refused": "refused"}, PhotosDecision("denoised", noisy_refused="refused")),
    ({"aligned": "noisy", "denoised_refused": "refused"}, PhotosDecision("noisy", denoised_refused="refused")),
    ({"aligned": "denoised", "registered": {"denoised": 8, "noisy": 7},
      "centre_std_over_spacing": {"denoised": 0.0061, "noisy": None}, "reason": COMPARISON.reason},
     PhotosDecision("denoised", comparison=COMPARISON)),
]
LEGACY_INHERITED = [
    ({"focal_px": 212.0, "focal_log_std": 0.02, "mode": "auto",
      "estimate_discarded": {"focal_px": 168.0, "focal_log_std": 0.046}, "used": True}, INHERITED),
    ({"focal_px": 212.0, "focal_log_std": 0.02, "mode": "auto", "used": False, "estimate_focal_log_std": 0.01},
     InheritedCalibration(212.0, 0.02, "auto", used=False, estimate_focal_log_std=0.01)),
    ({"focal_px": 212.0, "focal_log_std": None, "mode": "auto", "used": False, "estimate_focal_log_std": None},
     InheritedCalibration(212.0, None, "auto", used=False)),
    ({"focal_px": 212.0, "focal_log_std": 0.02, "mode": "auto", "estimate_refused": "not determined", "used": True},
     InheritedCalibration(212.0, 0.02, "auto", used=True, estimate_refused="not determined")),
    ({"focal_px": 212.0, "focal_log_std": None, "mode": "always", "used": True},
     InheritedCalibration(212.0, None, "always", used=True)),
]
LEGACY_GEOMETRY = {"used_previous": True, "reason": GEOMETRY.reason, "views": ["a.png", "b.png", "c.png"],
                   "previous_registered": 3, "current_registered": 2, "previous_centre_std": 0.012,
                   "current_centre_std": None, "current_error": "degenerate"}


def _through_text(data: dict) -> dict:
    return json.loads(json.dumps(data))


@pytest.mark.parametrize(("legacy", "record"), LEGACY_PHOTOS)
def test_photos_decision_round_trip_and_keys(legacy, record):
    assert record.to_json() == legacy  # the on-disk record is unchanged: same keys, same values
    assert PhotosDecision.from_json(_through_text(record.to_json())) == record
    assert PhotosDecision.from_json(legacy) == record


def test_photos_comparison_round_trip():
    assert PhotosComparison.from_json(_through_text(COMPARISON.to_json())) == COMPARISON
    assert COMPARISON.centre_std_over_spacing.of("denoised") == 0.0061 and COMPARISON.registered.of("noisy") == 7
    assert PerPhotos.from_json(_through_text(COMPARISON.registered.to_json())) == COMPARISON.registered


def test_photos_decision_names_the_photos():
    with pytest.raises(ValueError, match="aligned"):
        PhotosDecision("clean")  # type: ignore[arg-type]


def test_geometry_choice_round_trip_and_keys():
    assert GEOMETRY.to_json() == LEGACY_GEOMETRY
    assert GeometryChoice.from_json(_through_text(GEOMETRY.to_json())) == GEOMETRY
    # a record written before `current_error` was recorded
    older = {k: v for k, v in LEGACY_GEOMETRY.items() if k != "current_error"}
    assert GeometryChoice.from_json(older).current_error is None


@pytest.mark.parametrize(("legacy", "record"), LEGACY_INHERITED)
def test_inherited_calibration_round_trip_and_keys(legacy, record):
    assert record.to_json() == legacy
    assert list(record.to_json()) == list(legacy)  # and in the same order
    assert InheritedCalibration.from_json(_through_text(record.to_json())) == record
    assert InheritedCalibration.from_json(legacy) == record


def test_focal_estimate_round_trip():
    for estimate in (FocalEstimate(168.0, 0.046), FocalEstimate(None, None)):
        assert FocalEstimate.from_json(_through_text(estimate.to_json())) == estimate


def test_inherited_calibration_refuses_contradictory_records():
    with pytest.raises(ValueError, match="used=False"):
        InheritedCalibration(212.0, 0.02, "auto", used=True, estimate_focal_log_std=0.01)
    with pytest.raises(ValueError, match="used=True"):
        InheritedCalibration(212.0, 0.02, "auto", used=False, estimate_refused="not determined")


def test_align_decisions_round_trip():
    full = AlignDecisions(photos=PhotosDecision("noisy", comparison=COMPARISON), geometry=GEOMETRY,
                          inherited=INHERITED)
    for decisions in (AlignDecisions(), full, AlignDecisions(geometry=GEOMETRY)):
        assert AlignDecisions.from_json(_through_text(decisions.to_json())) == decisions
    assert AlignDecisions().to_json() == {}
    assert set(full.to_json()) == {PHOTOS_KEY, GEOMETRY_KEY, INHERITED_KEY}


def _alignment(stats: AlignStats) -> AlignResult:
    cam = Camera.pinhole(100.0, 100.0, 32.0, 24.0, 64, 48)
    images = [PosedImage(f"{v}.png", 1, np.hstack([np.eye(3), [[0.1 * i], [0.0], [0.0]]])) for i, v in enumerate("abc")]
    xyz = np.array([[0.0, 0.0, 4.0], [0.5, 0.2, 5.0]])
    rgb = np.array([[10, 20, 30], [40, 50, 60]], np.uint8)
    return AlignResult(SparseModel({1: cam}, images, xyz, rgb), xyz, rgb, np.ones(2), stats)


def test_the_stage_writes_its_records_as_top_level_keys_of_align_json(tmp_path):
    stats = align_stats(n_registered=3, bundle_adjustment=bundle_stats(focal_log_std=0.02))
    decisions = AlignDecisions(photos=PhotosDecision("denoised", comparison=COMPARISON), geometry=GEOMETRY,
                               inherited=INHERITED)
    staged = AlignStageResult(_alignment(stats), decisions)
    out = staged.write(tmp_path / "align")
    raw = json.loads((out / "align.json").read_text())
    assert raw == _through_text(staged.align_json())
    assert raw[PHOTOS_KEY] == LEGACY_PHOTOS[-1][0] and raw[GEOMETRY_KEY] == LEGACY_GEOMETRY
    assert raw[INHERITED_KEY] == LEGACY_INHERITED[0][0] and "annotations" not in raw
    # mvgeo reads its fields (NaN figures aside: compare through the JSON text), the stage its records
    assert json.dumps(AlignStats.read(out / "align.json").to_json()) == json.dumps(stats.to_json())
    assert AlignDecisions.read(out / "align.json") == decisions


def test_an_align_json_written_before_the_records_were_typed_still_reads(tmp_path):
    """A run folder's align.json with the records as literal dicts (the align stage's earlier writer)."""
    stats = align_stats(n_registered=3, known_intrinsics=True)
    legacy_inherited = LEGACY_INHERITED[-1][0]
    doc = {**stats.to_json(), PHOTOS_KEY: {"aligned": "noisy"}, GEOMETRY_KEY: LEGACY_GEOMETRY,
           INHERITED_KEY: legacy_inherited}
    (tmp_path / "align.json").write_text(json.dumps(doc, indent=2, allow_nan=True))
    assert json.dumps(AlignStats.read(tmp_path / "align.json").to_json()) == json.dumps(stats.to_json())
    decisions = AlignDecisions.read(tmp_path / "align.json")
    assert decisions == AlignDecisions(photos=PhotosDecision("noisy"), geometry=GEOMETRY,
                                       inherited=InheritedCalibration(212.0, None, "always", used=True))
    # written again, the document is the same
    again = AlignStats.read(tmp_path / "align.json").to_json(extra_keys=decisions.to_json())
    assert json.dumps(again, sort_keys=True) == json.dumps(doc, sort_keys=True)
    # one without any of the records reads as no decisions
    assert AlignDecisions.from_json(stats.to_json()) == AlignDecisions()
