"""`mvgeo.align.stats.AlignStats`: one JSON serializer and its inverse; a caller's extra keys at the top level."""

import dataclasses
import json
import math

import pytest

from mvgeo.align.stats import (
    AlignStats,
    BundleStats,
    CandidateSummary,
    DenseStereoStats,
    FailedPair,
    InconsistentPair,
    LocatedView,
    PrincipalPointStats,
    RejectedPair,
    Unregistered,
)


def _stats(**changes) -> AlignStats:
    """An `AlignStats` with every nested type filled in (finite figures: NaN != NaN)."""
    s = AlignStats(
        n_images=4, n_registered=3, input_size_wh=[256, 192], align_size_wh=[256, 192], pointmap_size_wh=[96, 72],
        n_pairs=6, n_pairs_ok=4, n_pairs_verified=5,
        failed_pairs=[FailedPair("a.png", "d.png", "only 3 SIFT matches (need 20)")],
        pairs_rejected_by_loops=[RejectedPair("b.png", "c.png", 2, 1)],
        unregistered=[Unregistered("d.png", "not connected to the registered images by any usable pair")],
        iterations=60, init_loss=1.5, final_loss=0.25, focal_px={"a.png": 210.5, "b.png": 210.5, "c.png": 210.5},
        known_intrinsics=False, shared_focal=True,
        bundle_adjustment=BundleStats(120, 300, 2.5, 0.4, 1.9, 0.3, 0.01, "lm", centre_std_ratio=[0.01, 0.02, 0.03],
                                      dense_depth_scale=[1.0, 0.98, 1.01], dense_depth_log_mad=[0.01, None, 0.02]),
        dense_stereo=DenseStereoStats([256, 192], 4, [0.8, 0.7, 0.75], [0.1, 0.0, 0.05], ["c.png"],
                                      track_depth_ratio=[1.0, 1.001, 0.999], track_log_mad=[0.01, None, 0.02]),
        focal_determined_by_pairs=True, sensitive_features=False, initial_poses="averaged",
        candidates=[CandidateSummary("chain", 205.0, 210.5, False, 0, 0.61, ["pairs_contradicted"]),
                    CandidateSummary("averaged", 205.0, 210.4, False, 0, 0.99, [], chosen=True,
                                     start_made_by="averaged_positions"),
                    CandidateSummary("chain", None, None, False, 0, 0.0, [], error="the pair graph is disconnected")],
        pairs_dropped_as_inconsistent=[["a.png", "c.png"]], pair_consistency_min=0.62,
        pairs_inconsistent=[InconsistentPair("a.png", "c.png", 0.4, 12.5), InconsistentPair("b.png", "c.png", 0.3,
                                                                                             None)],
        views_located_by_points=[LocatedView("c.png", 154, 63.8, 4000, "re-posed"),
                                 LocatedView("c.png", 113, 0.11, 4100, "kept")],
        n_points=5000, mean_confidence=4.5, timings_s={"load": 0.1, "total": 2.0},
        config={"max_size_px": 320, "pairs": {"kind": "complete"}, "seed": 0},
        principal_point=PrincipalPointStats([-16.5, 9.6], [1.8, 3.3], True, "determined: ..."))
    return dataclasses.replace(s, **changes)


def test_json_round_trip_is_the_identity():
    s = _stats()
    assert AlignStats.from_json(s.to_json()) == s
    text = json.dumps(s.to_json())  # plain JSON
    back = AlignStats.from_json(json.loads(text))
    assert back == s
    assert isinstance(back.bundle_adjustment, BundleStats) and isinstance(back.candidates[1], CandidateSummary)
    assert back.unregistered[0].name == "d.png" and back.bundle_adjustment.centre_std_ratio == [0.01, 0.02, 0.03]
    assert isinstance(back.principal_point, PrincipalPointStats) and back.principal_point.kept
    for empty in (_stats(bundle_adjustment=None, dense_stereo=None, principal_point=None),
                  _stats(failed_pairs=[], candidates=[], unregistered=[], pairs_inconsistent=[])):
        assert AlignStats.from_json(json.loads(json.dumps(empty.to_json()))) == empty


def test_the_file_is_one_flat_document_with_the_extra_keys_on_top(tmp_path):
    s = _stats()
    s.write(tmp_path / "align.json", extra_keys={"geometry_round": 2, "calibration": {"source": "reused"}})
    raw = json.loads((tmp_path / "align.json").read_text())
    assert raw["geometry_round"] == 2 and raw["calibration"] == {"source": "reused"} and "annotations" not in raw
    assert raw == {**s.to_json(), "geometry_round": 2, "calibration": {"source": "reused"}}
    assert raw["bundle_adjustment"]["reproj_rms_after_px"] == 0.4  # nested figures keep their names
    assert raw["candidates"][1] == {"start": "averaged", "pairs_focal_px": 205.0, "bundle_focal_px": 210.4,
                                    "refocused": False, "n_pairs_dropped": 0, "explained_fraction": 0.99,
                                    "reasons": [], "chosen": True, "error": "", "start_made_by": "averaged_positions"}
    # The fields read back alike; the extra keys are the caller's to read (`from_json` leaves them out).
    assert AlignStats.read(tmp_path / "align.json") == s
    assert AlignStats.from_json(raw) == AlignStats.from_json(s.to_json()) == s


def test_nan_figures_are_written_and_read_back_as_nan(tmp_path):
    s = _stats(pair_consistency_min=float("nan"), mean_confidence=float("nan"))
    s.write(tmp_path / "align.json")
    assert "NaN" in (tmp_path / "align.json").read_text()
    back = AlignStats.read(tmp_path / "align.json")
    assert math.isnan(back.pair_consistency_min) and math.isnan(back.mean_confidence)
    assert dataclasses.replace(back, pair_consistency_min=0.0, mean_confidence=0.0) == dataclasses.replace(
        s, pair_consistency_min=0.0, mean_confidence=0.0)


def test_extra_keys_may_not_replace_a_field(tmp_path):
    with pytest.raises(ValueError, match=r"extra keys may not replace align.json fields: \['n_points'\]"):
        _stats().to_json(extra_keys={"n_points": 1, "note": "x"})
    with pytest.raises(ValueError, match=r"\['n_points'\]"):
        _stats().write(tmp_path / "align.json", extra_keys={"n_points": 1})
    assert not (tmp_path / "align.json").exists()


def test_a_document_without_a_field_is_refused():
    data = _stats().to_json()
    del data["candidates"], data["initial_poses"]
    with pytest.raises(KeyError, match=r"\['candidates', 'initial_poses'\]"):
        AlignStats.from_json(data)
