"""Rounds >= 2 keep the better-determined focal length (eval.pipeline.calibration) and the align
stage's use of it, with a recording stand-in for `align_images` (the decision logic, not alignment)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from eval.pipeline import preset, run_pipeline
from eval.pipeline.align_decisions import INHERITED_KEY, AlignDecisions, FocalEstimate, InheritedCalibration
from eval.pipeline.align_stage import _align_with_previous_calibration
from eval.pipeline.calibration import focal_log_std, prefer_previous, previous_calibration
from mvgeo.camera import Camera
from mvgeo.common.errors import ConfigError, DegenerateGeometryError, InputError
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model
from tests.common.align_stats import align_stats, bundle_stats
from tests.eval._tiny_stages import TinyStages, make_scene


def _align_dir(folder, focals=(210.0, 214.0, 212.0), std=0.02, known=False):
    cams = {i + 1: Camera.pinhole(f, f, 128.0, 96.0, 256, 192) for i, f in enumerate(focals)}
    images = [PosedImage(f"v{i}.png", i + 1, np.hstack([np.eye(3), [[i], [0.0], [0.0]]])) for i in range(len(focals))]
    write_sparse_model(folder / "sparse" / "0", SparseModel(cams, images, np.zeros((0, 3)), np.zeros((0, 3), np.uint8)),
                       binary=True)
    if known:  # a calibration this round inherited, with the figure of the round that estimated it
        inherited = InheritedCalibration(focal_px=212.0, focal_log_std=std, mode="always", used=True)
        align_stats(known_intrinsics=True).write(folder / "align.json",
                                                 extra_keys=AlignDecisions(inherited=inherited).to_json())
    else:
        align_stats(bundle_adjustment=bundle_stats(focal_log_std=std)).write(folder / "align.json")
    return folder


def _inherited(std: float | None) -> InheritedCalibration:
    return InheritedCalibration(focal_px=212.0, focal_log_std=std, mode="auto", used=True)


def test_focal_log_std_sources():
    estimated = align_stats(bundle_adjustment=bundle_stats(focal_log_std=0.03))
    assert focal_log_std(estimated, inherited=None) == 0.03
    assert focal_log_std(align_stats(), inherited=None) is None  # no bundle adjustment: unknown
    nan = align_stats(bundle_adjustment=bundle_stats(focal_log_std=float("nan")))
    assert focal_log_std(nan, inherited=None) is None
    assert focal_log_std(align_stats(known_intrinsics=True), inherited=_inherited(0.01)) == 0.01
    assert focal_log_std(align_stats(known_intrinsics=True), inherited=_inherited(None)) is None
    assert focal_log_std(align_stats(known_intrinsics=True), inherited=None) is None  # a user's calibration
    # an estimated focal is the bundle adjustment's, whatever was offered
    assert focal_log_std(estimated, inherited=_inherited(0.01)) == 0.03


@pytest.mark.parametrize(("mode", "prev", "cur", "expected"), [
    ("auto", 0.02, 0.05, True),    # round 1 better determined (the seed-1 case)
    ("auto", 0.03, 0.02, False),   # this round's better
    ("auto", 0.02, None, True),    # this round's unknown
    ("auto", None, 0.05, False),   # previous unknown: keep the estimate
    ("never", 0.001, 0.5, False),
    ("always", None, 0.001, True),
])
def test_prefer_previous(mode, prev, cur, expected):
    assert prefer_previous(mode, prev, cur) is expected


def test_previous_calibration_is_the_median_camera(tmp_path):
    cam, std = previous_calibration(_align_dir(tmp_path / "a"))
    assert (cam.model, cam.width, cam.height) == ("PINHOLE", 256, 192)
    assert cam.fx == cam.fy == 212.0 and (cam.cx, cam.cy) == (128.0, 96.0) and std == 0.02
    # An inherited calibration carries the first round's figure on to round 3.
    assert previous_calibration(_align_dir(tmp_path / "b", known=True, std=0.015))[1] == 0.015
    (tmp_path / "b" / "align.json").unlink()
    with pytest.raises(InputError, match="align.json"):
        previous_calibration(tmp_path / "b")


class _FakeAlign:
    """Records calls; returns a result whose focal uncertainty is `std` (or raises `error`)."""

    def __init__(self, std=None, error=None):
        self.calls, self.std, self.error = [], std, error

    def __call__(self, files, cfg, intrinsics=None):
        self.calls.append(intrinsics)
        if intrinsics is None:
            if self.error is not None:
                raise self.error
            return SimpleNamespace(stats=align_stats(focal_px={"a": 170.0, "b": 166.0},
                                                     bundle_adjustment=bundle_stats(focal_log_std=self.std)))
        return SimpleNamespace(stats=align_stats(known_intrinsics=True, focal_px={"a": intrinsics.fx}))


def test_align_stage_keeps_the_better_focal(tmp_path):
    prev = _align_dir(tmp_path / "prev", std=0.02)
    worse = _FakeAlign(std=0.046)
    res = _align_with_previous_calibration(worse, [], None, prev, "auto")
    assert worse.calls[0] is None and worse.calls[1].fx == 212.0  # estimated, then re-aligned with round 1's
    info = res.decisions.inherited
    assert info.used and info.focal_log_std == 0.02 and info.focal_px == 212.0 and info.mode == "auto"
    assert info.estimate_discarded == FocalEstimate(focal_px=168.0, focal_log_std=0.046)
    # align.json keeps the record's keys and values
    assert res.decisions.to_json()[INHERITED_KEY] == {
        "focal_px": 212.0, "focal_log_std": 0.02, "mode": "auto",
        "estimate_discarded": {"focal_px": 168.0, "focal_log_std": 0.046}, "used": True}
    assert focal_log_std(res.alignment.stats, inherited=info) == 0.02  # what round 3 will compare against

    better = _FakeAlign(std=0.01)
    res = _align_with_previous_calibration(better, [], None, prev, "auto")
    assert better.calls == [None] and res.decisions.inherited.used is False
    assert res.decisions.inherited.estimate_focal_log_std == 0.01

    always = _FakeAlign(std=0.001)
    res = _align_with_previous_calibration(always, [], None, prev, "always")
    assert len(always.calls) == 1 and always.calls[0].fx == 212.0 and res.decisions.inherited.used

    refused = _FakeAlign(error=DegenerateGeometryError("the focal length is not determined by these views"))
    res = _align_with_previous_calibration(refused, [], None, prev, "auto")
    assert refused.calls[1].fx == 212.0
    assert "not determined" in res.decisions.inherited.estimate_refused


def test_pipeline_passes_the_previous_alignment_to_later_rounds_only(tmp_path):
    scene = make_scene(tmp_path / "images", n=5)
    seen = []
    tiny = TinyStages()

    def align(ctx):
        seen.append((ctx.work_dir.parent.name, ctx.inputs.get("previous_align"), ctx.settings.reuse_intrinsics))
        return tiny.align(ctx)

    stages = dataclasses.replace(tiny.stages(), align=align)
    out = tmp_path / "out"
    cfg = preset("fast", views=3, rounds=3)
    run_pipeline(scene, out, cfg, stages=stages)
    assert seen == [("round1", None, None), ("round2", out / "round1" / "align", "auto"),
                    ("round3", out / "round2" / "align", "auto")]
    # The setting belongs to rounds >= 2: changing it re-runs their alignments, never round 1.
    tiny2 = TinyStages()
    stages2 = dataclasses.replace(tiny2.stages(), align=align)
    seen.clear()
    never = dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, reuse_intrinsics="never"))
    run_pipeline(scene, out, never, stages=stages2)
    assert [s[0] for s in seen] == ["round2", "round3"]
    # Round 1 and round 2's refinement are reused; round 3's selection and refinement follow round
    # 2's new scene.
    assert tiny2.calls["denoise"] == 0 and tiny2.calls["refine"] == 1 and tiny2.calls["select"] == 1


def test_unknown_reuse_mode_is_a_config_error():
    cfg = preset("fast")
    with pytest.raises(ConfigError, match="reuse_intrinsics"):
        dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, reuse_intrinsics="sometimes"))
