"""`eval.pipeline.quality`: the report's self-checks of a run (no ground truth) and its camera plot."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio

from eval.pipeline.quality import (
    camera_plot_png,
    fit_psnr_db,
    plot_axes,
    quality_lines,
    round_camera_plot,
    round_quality,
)
from eval.pipeline.rounds import RoundResult
from eval.pipeline.stage import StageResult
from mvgeo.align.stats import FocalPriorStats, InconsistentPair, Unregistered
from mvgeo.camera import Camera
from mvgeo.common.imageio import read_image, write_image
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model
from tests.common.align_stats import align_stats, bundle_stats


def _look_at(centre: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(3, 4) cam_from_world of an OpenCV camera (x right, y down, z forward) at `centre` looking at `target`."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # down
    R = np.stack([x, y, z])
    return np.concatenate([R, (-R @ centre)[:, None]], axis=1)


def _ring(n: int = 8, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    up = np.asarray(up)
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([_look_at(np.array([3 * np.cos(t), 3 * np.sin(t), 0.5]), np.zeros(3), up) for t in a])


def test_plot_axes_put_up_against_the_cameras_image_down_axis():
    # An orbit around +z: up is +z; forward, right and up are orthonormal and right-handed (right = fwd x up).
    fwd, right, up = plot_axes(_ring())
    np.testing.assert_allclose(up, [0, 0, 1], atol=0.02)  # the cameras look slightly down: up tilts a little
    assert abs(fwd @ up) < 1e-12 and abs(right @ up) < 1e-12 and abs(fwd @ right) < 1e-12
    np.testing.assert_allclose(np.cross(fwd, up), right, atol=1e-12)
    # Forward-facing cameras on a line, looking along +x with world up -y: forward is +x, up is -y.
    cams = np.stack([_look_at(np.array([0.0, 0.0, z]), np.array([10.0, 0.0, z]), np.array([0.0, -1.0, 0.0]))
                     for z in np.linspace(-1, 1, 5)])
    fwd, right, up = plot_axes(cams)
    np.testing.assert_allclose(fwd, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(up, [0, -1, 0], atol=1e-12)


def test_fit_psnr_matches_scikit_image_and_skips_unmatched_views(tmp_path):
    rng = np.random.default_rng(0)
    clean = {f"v{i}": rng.random((24, 32, 3), dtype=np.float32) for i in range(3)}
    for name, img in clean.items():
        write_image(tmp_path / "photos" / f"{name}.png", img)
        write_image(tmp_path / "renders" / f"{name}.png", np.clip(img + rng.normal(0, 0.05, img.shape), 0, 1))
    write_image(tmp_path / "renders" / "extra.png", clean["v0"])  # no photo of that name: left out
    write_image(tmp_path / "photos" / "v2.png", np.zeros((12, 16, 3), np.float32))  # another size: left out
    got = fit_psnr_db(tmp_path / "renders", tmp_path / "photos")
    assert sorted(got) == ["v0", "v1"]
    for name in got:  # the PNGs as read back (8-bit levels), against scikit-image's PSNR
        ref = peak_signal_noise_ratio(read_image(tmp_path / "photos" / f"{name}.png").astype(np.float64),
                                      read_image(tmp_path / "renders" / f"{name}.png").astype(np.float64),
                                      data_range=1.0)
        assert got[name] == pytest.approx(ref, rel=1e-9)
    assert fit_psnr_db(tmp_path / "missing", tmp_path / "photos") == {}


def _stage(name: str, outputs: dict, summary: dict) -> StageResult:
    return StageResult(name=name, key="0" * 64, outputs=outputs, summary=summary, skipped=False, seconds=1.0,
                       outputs_digest="")


def _round(tmp_path: Path, stats, *, with_splat: bool = True, photos: dict | None = None) -> RoundResult:
    rd = tmp_path / "round1"
    (rd / "align").mkdir(parents=True)
    stats.write(rd / "align" / "align.json")
    cams = _ring(4)
    names = [f"{i:03d}.png" for i in range(4)]
    model = SparseModel({1: Camera.pinhole(100.0, 100.0, 32.0, 24.0, 64, 48)},
                        [PosedImage(n, 1, c) for n, c in zip(names, cams, strict=True)],
                        np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    write_sparse_model(rd / "align" / "sparse" / "0", model, binary=True)
    np.savez(rd / "align" / "points.npz", xyz=np.random.default_rng(1).normal(size=(500, 3)))
    stages = {"denoise": _stage("denoise", {}, {"train": {"loss": {"first": 1.25, "last": 0.5, "count": 400}},
                                               "objective": "r2r", "dark_clipped_fraction": 0.024}),
              "align": _stage("align", {"align": rd / "align"},
                              {"registered": 4, "photos": photos or {"aligned": "noisy"}})}
    if with_splat:
        img = np.full((48, 64, 3), 0.5, np.float32)
        for k, n in enumerate(names):
            write_image(rd / "denoised" / n, img)
            write_image(rd / "renders" / n, img + (0.01 * (k + 1) if k != 2 else 0.2))  # view 002 fits worst
        stages["splat"] = _stage("splat", {"sparse": rd / "sparse"}, {
            "train": {"num_gaussians": {"first": 900.0, "last": 1234.0, "count": 11}}, "timings_s": {"optimize": 42.0}})
    return RoundResult(index=1, dir=rd, stages=stages)


def test_round_quality_reads_the_stages_and_align_json(tmp_path):
    stats = align_stats(n_registered=4, focal_px={f"{i:03d}.png": 512.0 for i in range(4)},
                        bundle_adjustment=dataclasses.replace(
                            bundle_stats(focal_log_std=0.012, centre_std_ratio=[0.01, 0.04, 0.02, 0.03]),
                            n_points=321, n_observations=999, reproj_rms_after_px=0.61, reproj_median_after_px=0.27,
                            views=["003.png", "000.png", "001.png", "002.png"]))
    stats = dataclasses.replace(stats, n_images=5, align_size_wh=[64, 48], n_pairs=10, n_pairs_verified=7,
                                n_pairs_ok=5, focal_determined_by_pairs=False,
                                unregistered=[Unregistered("004.png", "no usable pair")],
                                pairs_inconsistent=[InconsistentPair("000.png", "001.png", 0.83, 4.0)])
    q = round_quality(_round(tmp_path, stats))
    a = q.align
    assert (a.n_registered, a.n_images, a.unregistered, a.photos) == (4, 5, [("004.png", "no usable pair")], "noisy")
    assert a.focal_px == 512.0 and a.focal_log_std == 0.012 and "generic prior" in a.focal_source
    assert (a.n_tracks, a.n_observations, a.reproj_rms_px, a.reproj_median_px) == (321, 999, 0.61, 0.27)
    assert (a.n_pairs, a.n_pairs_verified, a.n_pairs_dense) == (10, 7, 5)
    # Largest centre uncertainty first, named through `BundleStats.views` (not the order of focal_px).
    assert a.least_constrained == [("000.png", 0.04), ("002.png", 0.03), ("001.png", 0.02)]
    assert q.denoise.objective == "r2r" and (q.denoise.loss_first, q.denoise.loss_last, q.denoise.steps) == (
        1.25, 0.5, 400)
    s = q.splat
    assert s.n_gaussians == 1234 and s.seconds == 42.0 and s.worst[0][0] == "002"
    assert s.fit_psnr_db["000"] > s.fit_psnr_db["001"] > s.fit_psnr_db["003"] > s.fit_psnr_db["002"]
    text = "\n".join(quality_lines([q]))
    for part in ("**4 of 5 views registered**", "`004.png` left out: no usable pair", "512.0 px at 64x48",
                 "log-std 0.012 (1.2 %)", "321 tracks, 999 observations", "RMS 0.610 px", "7 of 10 verified",
                 "`000.png`-`001.png` (83 % of its matches)", "`000.png` 4.00 %", "objective r2r (2.4 %",
                 "training loss 1.25 -> 0.5 over 400 steps",
                 "1234 Gaussians in 42 s", "lowest `002`"):
        assert part in text, part
    assert q.to_json()["align"]["least_constrained"][0] == ["000.png", 0.04]


def test_the_report_says_which_photos_round1_kept_and_why(tmp_path):
    """`AlignSettings.photos` "better_of": the report names the kept alignment and the reason recorded."""
    stats = align_stats(n_registered=4, focal_px={f"{i:03d}.png": 512.0 for i in range(4)})
    reason = "the denoised photos' alignment: its camera centres are better determined (bundle adjustment)"
    q = round_quality(_round(tmp_path, stats, with_splat=False, photos={
        "aligned": "denoised", "registered": {"denoised": 4, "noisy": 4},
        "centre_std_over_spacing": {"denoised": 0.006, "noisy": 0.007}, "reason": reason}))
    assert (q.align.photos, q.align.photos_reason) == ("denoised", reason)
    text = "\n".join(quality_lines([q]))
    assert "alignment (denoised photos)" in text and f"the noisy and the denoised photos' alignments, {reason}" in text
    plain = round_quality(_round(tmp_path / "plain", stats, with_splat=False))
    assert plain.align.photos_reason is None and "alignments," not in "\n".join(quality_lines([plain]))
    same = round_quality(_round(tmp_path / "same", stats, with_splat=False,
                                photos={"aligned": "noisy", "identical_photos": True}))
    assert same.align.photos_identical and not plain.align.photos_identical
    assert "are the noisy ones (passed through undenoised): aligned once" in "\n".join(quality_lines([same]))
    assert "alignment (the photos, undenoised)" in "\n".join(quality_lines([same]))
    assert "aligned once" not in "\n".join(quality_lines([plain]))


def test_focal_source_names_the_calibration_or_the_prior(tmp_path):
    known = dataclasses.replace(align_stats(n_registered=4, known_intrinsics=True, bundle_adjustment=bundle_stats(
        focal_log_std=0.0)), focal_px={"000.png": 500.0})
    q = round_quality(_round(tmp_path / "a", known, with_splat=False))
    assert "--intrinsics" in q.align.focal_source and math.isnan(q.align.focal_log_std) and q.splat is None
    exif = dataclasses.replace(align_stats(n_registered=4), focal_determined_by_pairs=False,
                               focal_prior=FocalPriorStats("exif", 28.0, 400.0))
    assert "exif focal (28 mm" in round_quality(_round(tmp_path / "b", exif)).align.focal_source
    pairs = align_stats(n_registered=4)  # focal_determined_by_pairs
    assert "from the pairs" in round_quality(_round(tmp_path / "c", pairs)).align.focal_source


def test_unreadable_align_json_is_a_clear_error(tmp_path):
    from mvgeo.common.errors import InputError

    rnd = _round(tmp_path, align_stats(n_registered=4))
    (rnd.dir / "align" / "align.json").write_text("{")
    with pytest.raises(InputError, match="cannot read the alignment's report") as e:
        round_quality(rnd)
    assert e.value.path == rnd.dir / "align" / "align.json"


def test_camera_plot_is_written_from_the_splat_or_the_alignment_cameras(tmp_path):
    rnd = _round(tmp_path, align_stats(n_registered=4), with_splat=False)
    path = round_camera_plot(tmp_path / "report", rnd)  # no splat: the alignment's cameras
    assert path == tmp_path / "report" / "report_files" / "cameras_round1.png"
    img = read_image(path)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 400 and img.std() > 0.01  # not blank
    assert round_camera_plot(tmp_path / "r2", RoundResult(index=2, dir=tmp_path, stages={})) is None
    one = SparseModel({1: Camera.pinhole(100.0, 100.0, 32.0, 24.0, 64, 48)},
                      [PosedImage("a.png", 1, _ring(1)[0])], np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    assert camera_plot_png(tmp_path / "one.png", one, None, title="one camera").is_file()  # no spread, no points


def test_with_the_fuse_extension_the_renders_are_compared_with_the_fused_photos(tmp_path):
    rnd = _round(tmp_path, align_stats(n_registered=4))
    for n in sorted(p.name for p in (rnd.dir / "renders").glob("*.png")):
        write_image(rnd.dir / "fused" / n, read_image(rnd.dir / "renders" / n))  # what the splat trained on
    assert all(v < 60 for v in round_quality(rnd).splat.fit_psnr_db.values())  # against denoised/
    fused = RoundResult(index=1, dir=rnd.dir, stages={**rnd.stages, "fuse": _stage("fuse", {}, {})})
    assert all(math.isinf(v) for v in round_quality(fused).splat.fit_psnr_db.values())


def test_round_one_reports_the_photos_noise_level(tmp_path):
    """Each photo's noise std as the default denoiser reads it (`r2r_noise_std`), in /255, recorded by the
    denoise stage and reported from its summary."""
    from eval.pipeline.quality import noise_levels

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:96, :128] / 128.0
    base = np.stack([0.3 + 0.3 * xx, 0.4 + 0.2 * yy, 0.5 + 0.1 * xx * yy], axis=-1)
    photos = {f"v{k}": np.clip(base + rng.normal(0, sigma / 255, base.shape), 0, 1).astype(np.float32)
              for k, sigma in enumerate((10, 20))}
    record = noise_levels(photos)
    from denoise.self_supervised import r2r_noise_std
    assert noise_levels(photos, [r2r_noise_std(p) for p in photos.values()]) == record  # the stage's estimates
    with pytest.raises(ValueError, match="1 noise estimates for 2 images"):
        noise_levels(photos, [0.1])
    levels, dependent = record.noise_std_255, record.signal_dependent
    # 10 %: the estimates are 9.88 and 19.94 here (measured); the bound is about an estimator on 128x96 px
    # of a smooth ramp, not a tight fit, while a wrong scale (/255) or swapped images would be off 2x or more.
    assert dependent == [] and levels["v0"] == pytest.approx(10, rel=0.1) and levels["v1"] == pytest.approx(20, rel=0.1)
    rnd = _round(tmp_path / "r", align_stats(n_registered=4))
    recorded = RoundResult(index=1, dir=rnd.dir, stages={**rnd.stages, "denoise": _stage(
        "denoise", {}, {**rnd.stages["denoise"].summary, **record.to_json()})})
    q = round_quality(recorded)
    assert q.denoise.noise_std_255 == levels
    assert f"median {np.median(list(levels.values())):.1f}/255" in "\n".join(quality_lines([q]))
    assert round_quality(rnd).denoise.noise_std_255 == {}  # a summary without the record


def test_the_report_says_the_photos_were_denoised_as_pixel_shuffled_sub_images(tmp_path):
    rnd = _round(tmp_path / "r", align_stats(n_registered=4))
    levels = {"1": 2.0, "2": 12.6, "3": 11.8}

    def with_summary(**extra):
        return round_quality(RoundResult(index=1, dir=rnd.dir, stages={**rnd.stages, "denoise": _stage(
            "denoise", {}, {**rnd.stages["denoise"].summary, **extra})}))

    q = with_summary(pd_stride=2, noise_level_by_stride_255=levels)
    assert q.denoise.pd_stride == 2 and q.denoise.noise_level_by_stride_255 == levels
    text = "\n".join(quality_lines([q]))
    assert "denoised as 2 x 2 pixel-shuffled sub-images" in text and "12.6/255 at stride 2" in text
    for q in (with_summary(pd_stride=1, noise_level_by_stride_255={"1": 20.0, "2": 20.1}), round_quality(rnd)):
        assert "pixel-shuffled" not in "\n".join(quality_lines([q]))  # stride 1, or not recorded: no line
    q = with_summary(pd_stride=1, noise_level_by_stride_255={"1": 1.0}, noise_level_luma_255=24.3)
    text = "\n".join(quality_lines([q]))
    assert "colour patches read 1.0/255" in text and "read on their luma, 24.3/255" in text
    assert "pixel-shuffled" not in text
    assert "luma" not in "\n".join(quality_lines([with_summary(pd_stride=2, noise_level_by_stride_255=levels)]))
    # Demosaiced noise saved as a JPEG: both lines, the level read on the sub-images' luma.
    q = with_summary(pd_stride=2, noise_level_by_stride_255={"1": 0.7, "2": 3.7}, noise_level_luma_255=19.5)
    text = "\n".join(quality_lines([q]))
    assert "denoised as 2 x 2 pixel-shuffled sub-images" in text
    assert "read on their luma, 19.5/255 (on the sub-images)" in text


def test_the_report_suggests_the_luma_model_for_jpegs_whose_noise_was_not_found(tmp_path):
    rnd = _round(tmp_path / "r", align_stats(n_registered=4))
    summary = {**rnd.stages["denoise"].summary, "pd_stride": 1, "noise_level_by_stride_255": {"1": 0.6, "2": 1.4},
               "noise_level_luma_hint_255": 19.6}
    q = round_quality(RoundResult(index=1, dir=rnd.dir, stages={**rnd.stages, "denoise": _stage("denoise", {},
                                                                                                    summary)}))
    assert q.denoise.noise_level_luma_hint_255 == 19.6
    text = "\n".join(quality_lines([q]))
    assert "colour patches read 0.6/255" in text and "sub-images read 19.6/255" in text
    assert "--pd-stride 2 --noise-model luma" in text
    assert "--noise-model" not in "\n".join(quality_lines([round_quality(rnd)]))


def test_the_report_suggests_the_luma_model_with_a_given_stride(tmp_path):
    """`--pd-stride 2` given alone on a camera's JPEGs: the levels were read on the given stride only
    (`denoise.pixel_shuffle.stride_for`), and the bold line names that stride and `--noise-model luma`."""
    rnd = _round(tmp_path / "r", align_stats(n_registered=4))
    summary = {**rnd.stages["denoise"].summary, "pd_stride": 2, "noise_level_by_stride_255": {"2": 1.4},
               "noise_level_luma_hint_255": 19.6}
    q = round_quality(RoundResult(index=1, dir=rnd.dir, stages={**rnd.stages, "denoise": _stage("denoise", {},
                                                                                                    summary)}))
    text = "\n".join(quality_lines([q]))
    assert "**--pd-stride 2 was given" in text and "colour patches read 1.4/255" in text
    assert "luma reads 19.6/255" in text and "add --noise-model luma" in text and "nan" not in text
