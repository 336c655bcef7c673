"""`denoise-gs run --intrinsics`: the photos' calibration, checked up front, scaled to the working photos,
handed to every round's alignment instead of an estimated focal, its content in the align stages' keys."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from eval.cli import main
from eval.pipeline import preset, run_pipeline
from eval.pipeline.align_stage import align as align_stage
from eval.pipeline.align_stage import working_camera
from eval.pipeline.stage import StageContext
from eval.pipeline.stage_settings import round_settings
from mvgeo.common.errors import InputError
from tests.eval._tiny_stages import TinyStages, make_scene


def _cameras_txt(path: Path, *lines: str) -> Path:
    path.write_text("# Camera list with one line of data per camera:\n" + "".join(f"{ln}\n" for ln in lines))
    return path


@pytest.mark.parametrize(("lines", "message"), [
    ((), "does not exist"),
    (("1 OPENCV 48 40 50 50 24 20 0.1 0 0 0",), "lens distortion"),
    (("1 PINHOLE 96 80 100 100 48 40",), "for 96x80 images, the photos are 48x40"),
    (("1 PINHOLE 48 40 50 50 24 20", "2 PINHOLE 48 40 51 51 24 20"), "exactly one camera"),
])
def test_a_calibration_that_does_not_fit_the_photos_is_refused_before_any_output(tmp_path, capsys, lines, message):
    images = make_scene(tmp_path / "images", n=3)
    cams = tmp_path / "cameras.txt"
    if lines:
        _cameras_txt(cams, *lines)
    out = tmp_path / "out"
    code = main(["run", str(images), "--out", str(out), "--preset", "fast", "--intrinsics", str(cams)])
    err = capsys.readouterr().err
    assert code == 2 and message in err and "Traceback" not in err
    assert not out.exists()


def test_the_calibration_is_scaled_to_the_working_photos(tmp_path):
    make_scene(tmp_path / "small", n=1, size_wh=(24, 20))
    cams = _cameras_txt(tmp_path / "cameras.txt", "1 PINHOLE 48 40 50 52 24 20")
    cam = working_camera(cams, tmp_path / "small" / "view_000.png")
    assert cam.size_wh == (24, 20)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((25.0, 26.0, 12.0, 10.0))


def test_the_align_stage_aligns_with_the_calibration_and_no_focal_prior(tmp_path, monkeypatch):
    import mvgeo.align

    make_scene(tmp_path / "denoised", n=3)
    cams = _cameras_txt(tmp_path / "cameras.txt", "1 PINHOLE 48 40 50 52 24 20")
    calls = []

    class Refused(Exception):
        pass

    def fake_align(files, cfg, **kw):
        calls.append(kw)
        raise Refused  # what it was called with is what this test checks

    monkeypatch.setattr(mvgeo.align, "align_images", fake_align)
    settings = round_settings(preset("fast"), 1).align
    ctx = StageContext("align", tmp_path / "work", {"images": tmp_path / "denoised", "working": tmp_path / "denoised",
                                                     "intrinsics": cams}, settings, 0)
    with pytest.raises(Refused):
        align_stage(ctx)
    (kw,) = calls
    assert "focal_prior" not in kw and kw["intrinsics"].fx == 50.0 and kw["intrinsics"].fy == 52.0


def test_every_rounds_align_stage_gets_the_calibration_and_its_content_is_in_the_key(tmp_path):
    scene = make_scene(tmp_path / "images", n=5)
    cams = _cameras_txt(tmp_path / "cameras.txt", "1 PINHOLE 48 40 50 50 24 20")
    seen = []
    tiny = TinyStages()

    def align(ctx):
        seen.append((ctx.work_dir.parent.name, ctx.inputs.get("intrinsics")))
        return tiny.align(ctx)

    stages = dataclasses.replace(tiny.stages(), align=align)
    cfg = preset("fast", views=3, rounds=2)
    cfg = dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, intrinsics=str(cams)))
    out = tmp_path / "out"
    run_pipeline(scene, out, cfg, stages=stages)
    assert seen == [("round1", cams), ("round2", cams)]
    assert f"calibration: `{cams}` (given with --intrinsics" in (out / "report.md").read_text()
    # The same calibration in another folder: nothing to do again.
    (tmp_path / "calib").mkdir()
    moved = cams.rename(tmp_path / "calib" / "cameras.txt")
    seen.clear()
    run_pipeline(scene, out, dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, intrinsics=str(moved))),
                 stages=stages)
    assert seen == []
    # Another calibration: both rounds align again.
    _cameras_txt(moved, "1 PINHOLE 48 40 60 60 24 20")
    run_pipeline(scene, out, dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, intrinsics=str(moved))),
                 stages=stages)
    assert [s[0] for s in seen] == ["round1", "round2"]


def test_a_run_without_a_calibration_keeps_its_stage_keys(tmp_path):
    """Runs written before the option existed are resumed, not recomputed."""
    scene = make_scene(tmp_path / "images", n=4)
    tiny = TinyStages()
    out = tmp_path / "out"
    cfg = preset("fast", views=3, rounds=1)
    run_pipeline(scene, out, cfg, stages=tiny.stages())
    assert cfg.align.intrinsics is None
    tiny2 = TinyStages()
    run_pipeline(scene, out, cfg, stages=tiny2.stages())
    assert tiny2.calls["align"] == 0


def test_check_intrinsics_names_the_file(tmp_path):
    from eval.pipeline.validate import check_intrinsics

    cams = _cameras_txt(tmp_path / "c.txt", "1 SIMPLE_RADIAL 48 40 50 24 20 0.2")
    with pytest.raises(InputError, match="distortion") as info:
        check_intrinsics(cams, (48, 40))
    assert "c.txt" in str(info.value)


def test_photos_of_several_input_sizes_are_refused_with_one_calibration(tmp_path, capsys):
    """800x600 and 804x603 photos share a working size; one calibration cannot be both cameras."""
    images = make_scene(tmp_path / "images", n=2, size_wh=(96, 80))
    make_scene(tmp_path / "other", n=3, size_wh=(98, 82))
    (tmp_path / "other" / "view_002.png").rename(images / "view_009.png")
    cams = _cameras_txt(tmp_path / "cameras.txt", "1 PINHOLE 96 80 100 100 48 40")
    out = tmp_path / "out"
    code = main(["run", str(images), "--out", str(out), "--preset", "fast", "--max-size", "48",
                 "--intrinsics", str(cams)])
    err = capsys.readouterr().err
    assert code == 2 and "--intrinsics gives one camera" in err and not out.exists()
