"""Rounds >= 2 keep the better-determined alignment (`eval.pipeline.calibration.choose_geometry`) and the
align stage's use of it. The alignments are real bundle adjustments (`mvgeo.align.bundle`) of a small
synthetic forward-facing scene: one is made worse on purpose (noisier observations and a perturbed
start) and the rule must pick the other, which the ground truth confirms is closer."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eval.pipeline import preset, run_pipeline
from eval.pipeline.align_decisions import (
    GEOMETRY_KEY,
    PHOTOS_KEY,
    AlignDecisions,
    AlignStageResult,
    PerPhotos,
    PhotosDecision,
)
from eval.pipeline.align_stage import _align_keeping_better_geometry
from eval.pipeline.calibration import (
    centre_std_over_spacing,
    choose_geometry,
    restricted_ratios,
)
from eval.pipeline.config import AlignSettings, PipelineConfig
from mvgeo.align import AlignResult, write_align_result
from mvgeo.align.bundle import bundle_adjust
from mvgeo.align.stats import AlignStats
from mvgeo.camera import Camera
from mvgeo.common.errors import (
    AlignmentRefusedError,
    ConfigError,
    DegenerateGeometryError,
    DisconnectedViewsError,
    InputError,
)
from mvgeo.sparse_model import PosedImage, SparseModel
from tests.common.align_stats import align_stats, bundle_stats
from tests.eval._tiny_stages import TinyStages, make_scene

W, H, F = 160, 120, 140.0
ALL = [f"view_{i:03d}.png" for i in range(8)]
SELECTED = [ALL[i] for i in (0, 2, 4, 5, 7)]


def _rot(axis_angle: np.ndarray) -> np.ndarray:
    """Rodrigues: (3,) axis * angle in radians -> (3, 3)."""
    theta = float(np.linalg.norm(axis_angle))
    if theta < 1e-12:
        return np.eye(3)
    k = axis_angle / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def _scene():
    """Ground truth: 8 cameras on a 4 x 2 grid looking down +z at 120 points 4-6 units away."""
    rng = np.random.default_rng(0)
    centres = np.array([[x, y, 0.0] for y in (-0.15, 0.15) for x in (-0.45, -0.15, 0.15, 0.45)])
    cfw = np.stack([np.hstack([np.eye(3), -c[:, None]]) for c in centres])
    X = np.column_stack([rng.uniform(-1.5, 1.5, 120), rng.uniform(-1.1, 1.1, 120), rng.uniform(4.0, 6.0, 120)])
    return cfw, X


def _align(views: list[str], noise_px: float, start_deg: float, seed: int):
    """(SparseModel, align.json stats) of a bundle adjustment of `views` from observations with
    `noise_px` pixel noise, started from the true poses rotated by about `start_deg`."""
    rng = np.random.default_rng(seed)
    cfw_true, X = _scene()
    idx = [ALL.index(v) for v in views]
    uv = []
    for v in idx:
        x = X @ cfw_true[v, :, :3].T + cfw_true[v, :, 3]
        uv.append(F * x[:, :2] / x[:, 2:] + [W / 2, H / 2] + rng.normal(0.0, noise_px, (len(X), 2)))
    matches = [(a, b, np.hstack([uv[a], uv[b]])) for a in range(len(idx)) for b in range(a + 1, len(idx))]
    start = cfw_true[idx].copy()
    for k in range(1, len(idx)):
        start[k, :, :3] = _rot(np.deg2rad(start_deg) * rng.normal(size=3) / np.sqrt(3)) @ start[k, :, :3]
    ba = bundle_adjust(start, np.full(len(idx), F), (W, H), matches)
    centres = np.array([-m[:, :3].T @ m[:, 3] for m in ba.cam_from_world])
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    ratios = [float(s) / float(np.median(d.min(axis=1))) for s in ba.centre_std]  # mvgeo.align's definition
    cams = {k + 1: Camera.pinhole(f, f, W / 2, H / 2, W, H) for k, f in enumerate(ba.focal_px)}
    images = [PosedImage(views[k], k + 1, ba.cam_from_world[k]) for k in range(len(idx))]
    model = SparseModel(cams, images, X[:5].copy(), np.zeros((5, 3), np.uint8))
    return model, align_stats(n_registered=len(views),
                              bundle_adjustment=bundle_stats(centre_std_ratio=ratios, focal_log_std=0.01))


def _relative_rotation_error_deg(model: SparseModel, views: list[str]) -> float:
    """Mean over pairs of `views` of the angle between estimated and true relative rotations (frame-free)."""
    cfw_true, _ = _scene()
    errs = []
    for a in range(len(views)):
        for b in range(a + 1, len(views)):
            ra, rb = model.image(views[a]).cam_from_world[:, :3], model.image(views[b]).cam_from_world[:, :3]
            ta, tb = cfw_true[ALL.index(views[a]), :, :3], cfw_true[ALL.index(views[b]), :, :3]
            d = (rb @ ra.T) @ (tb @ ta.T).T
            errs.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    return float(np.mean(errs))


@pytest.fixture(scope="module")
def alignments():
    return {"round1_good": _align(ALL, 0.2, 0.0, 1), "round1_poor": _align(ALL, 2.5, 2.0, 2),
            "round2_good": _align(SELECTED, 0.1, 0.0, 3), "round2_poor": _align(SELECTED, 2.5, 2.0, 4)}


def _spacing_reference(model: SparseModel, names: list[str]) -> float:
    """Median over cameras of the nearest other camera's distance, by plain loops."""
    centres = {n: -model.image(n).cam_from_world[:, :3].T @ model.image(n).cam_from_world[:, 3] for n in names}
    nearest = [min(float(np.linalg.norm(centres[a] - centres[b])) for b in names if b != a) for a in names]
    return float(np.median(nearest))


def test_centre_std_over_spacing_matches_a_loop_reference(alignments):
    model, stats = alignments["round1_good"]
    got = centre_std_over_spacing(model, stats, SELECTED)
    ratios = dict(zip(model.names, stats.bundle_adjustment.centre_std_ratio, strict=True))
    scale = _spacing_reference(model, ALL) / _spacing_reference(model, SELECTED)
    assert set(got) == set(SELECTED)
    for v in SELECTED:
        assert got[v] == pytest.approx(ratios[v] * scale, rel=1e-12)
    # The restricted list is what the same figure reads on the restricted model.
    sub = SparseModel({im.camera_id: model.cameras[im.camera_id] for im in map(model.image, SELECTED)},
                      [model.image(v) for v in SELECTED])
    restricted = align_stats(bundle_adjustment=bundle_stats(centre_std_ratio=restricted_ratios(model, stats, SELECTED)))
    again = centre_std_over_spacing(sub, restricted, SELECTED)
    assert all(again[v] == pytest.approx(got[v], rel=1e-9) for v in SELECTED)
    # Unknown: no figure, a view missing, or fewer than 3 views.
    assert centre_std_over_spacing(model, align_stats(), SELECTED) is None
    assert centre_std_over_spacing(model, stats, [*SELECTED[:2], "other.png"]) is None
    assert centre_std_over_spacing(model, stats, SELECTED[:2]) is None


def test_a_worse_round2_alignment_gives_way_to_round1(alignments):
    prev, cur = alignments["round1_good"], alignments["round2_poor"]
    # The fixture is what it claims: round 2's poses are further from the truth.
    assert _relative_rotation_error_deg(cur[0], SELECTED) > 2 * _relative_rotation_error_deg(prev[0], SELECTED)
    choice = choose_geometry("auto", SELECTED, prev, cur)
    assert choice.used_previous and choice.previous_centre_std < choice.current_centre_std
    assert (choice.previous_registered, choice.current_registered) == (5, 5)
    # The paper's loop keeps its own.
    assert not choose_geometry("never", SELECTED, prev, cur).used_previous


def test_a_better_round2_alignment_is_kept(alignments):
    prev, cur = alignments["round1_poor"], alignments["round2_good"]
    assert _relative_rotation_error_deg(cur[0], SELECTED) < 0.5 * _relative_rotation_error_deg(prev[0], SELECTED)
    choice = choose_geometry("auto", SELECTED, prev, cur)
    assert not choice.used_previous and choice.current_centre_std <= choice.previous_centre_std


def test_rules_before_the_figures(alignments):
    prev, cur = alignments["round1_poor"], alignments["round2_good"]
    # This round registered fewer of the views: the previous round's, whatever the figures.
    four = SparseModel(cur[0].cameras, [cur[0].image(v) for v in SELECTED[:4]])
    assert choose_geometry("auto", SELECTED, prev, (four, cur[1])).used_previous
    # The previous round lacks a view: this round's own.
    seven = SparseModel(prev[0].cameras, [prev[0].image(v) for v in ALL if v != SELECTED[1]])
    assert not choose_geometry("auto", SELECTED, (seven, prev[1]), alignments["round2_poor"]).used_previous
    # An unknown figure loses to a known one; two unknown keep this round's.
    assert choose_geometry("auto", SELECTED, prev, (cur[0], align_stats())).used_previous
    assert not choose_geometry("auto", SELECTED, (prev[0], align_stats()), alignments["round2_poor"]).used_previous
    # This round failed: the previous round's when it holds every view.
    failed = choose_geometry("auto", SELECTED, prev, None, current_error="degenerate")
    assert failed.used_previous and failed.current_registered == 0 and failed.current_error == "degenerate"
    assert not choose_geometry("auto", SELECTED, (seven, prev[1]), None).used_previous


def _write_previous(folder, model, stats):
    n = len(model.points_xyz)
    write_align_result(folder, AlignResult(model, model.points_xyz, model.points_rgb, np.full(n, 3.0), stats))
    np.savez(folder / "points.npz", xyz=model.points_xyz, rgb=model.points_rgb, conf=np.full(n, 3.0))
    return folder


class _FakeAlign:
    """Stands in for `mvgeo.align.align_images`: returns a prepared alignment (or raises `error`)."""

    def __init__(self, alignment=None, error=None):
        self.alignment, self.error, self.calls = alignment, error, 0

    def __call__(self, files, cfg, intrinsics=None):
        self.calls += 1
        if self.error is not None:
            raise self.error
        model, stats = self.alignment
        return AlignResult(model, np.zeros((2, 3)), np.zeros((2, 3), np.uint8), np.ones(2), dataclasses.replace(stats))


def test_align_stage_hands_round1_geometry_to_round2(tmp_path, alignments):
    prev_dir = _write_previous(tmp_path / "prev", *alignments["round1_good"])
    files = [tmp_path / "round2" / v for v in SELECTED]
    res = _align_keeping_better_geometry(_FakeAlign(alignments["round2_poor"]), files, None, prev_dir, "never", "auto")
    prev_model = alignments["round1_good"][0]
    assert res.alignment.sparse_model.names == SELECTED
    for v in SELECTED:
        # (through the COLMAP binary files: quaternions, hence not bit-exact)
        np.testing.assert_allclose(res.alignment.sparse_model.image(v).cam_from_world,
                                   prev_model.image(v).cam_from_world, atol=1e-9)
        assert res.alignment.sparse_model.camera_of(v).fx == pytest.approx(prev_model.camera_of(v).fx, rel=1e-12)
    assert np.allclose(res.alignment.points_xyz, prev_model.points_xyz)  # round 1's cloud, in round 1's frame
    record = res.decisions.geometry
    assert record.used_previous and list(record.views) == SELECTED and res.alignment.stats.n_registered == 5
    assert res.decisions.to_json()[GEOMETRY_KEY]["views"] == SELECTED  # align.json: a list, as before
    # Round 3 compares against the same figure round 2 measured for round 1.
    again = choose_geometry("auto", SELECTED, (res.alignment.sparse_model, res.alignment.stats),
                            alignments["round2_poor"])
    assert again.previous_centre_std == pytest.approx(record.previous_centre_std, rel=1e-6)

    kept = _align_keeping_better_geometry(_FakeAlign(alignments["round2_good"]), files, None,
                                          _write_previous(tmp_path / "poor", *alignments["round1_poor"]),
                                          "never", "auto")
    assert kept.decisions.geometry.used_previous is False
    assert kept.alignment.sparse_model is alignments["round2_good"][0]

    paper = _align_keeping_better_geometry(_FakeAlign(alignments["round2_poor"]), files, None, prev_dir,
                                           "never", "never")
    assert paper.alignment.sparse_model is alignments["round2_poor"][0]
    assert not paper.decisions.geometry.used_previous


def _listed_in(stats, order: list[str], names: list[str]):
    """`stats` with its per-view ratios listed in `order` (recorded as `bundle_adjustment.views`), as
    `mvgeo.align` lists them in its input order; `names`: the order they are listed in now."""
    ba = stats.bundle_adjustment
    at = dict(zip(names, ba.centre_std_ratio, strict=True))
    return dataclasses.replace(stats, bundle_adjustment=dataclasses.replace(
        ba, centre_std_ratio=[at[v] for v in order], views=list(order)))


def test_ratios_follow_the_views_the_alignment_lists_them_for(tmp_path, alignments):
    """`mvgeo.align` lists `centre_std_ratio` in its input order (`bundle_adjustment.views`): the pipeline's
    stem order, which is not the sparse model's name order (`v.png` before `v-1.png`). Each figure belongs
    to the view it was listed for, whatever the model's order."""
    model, stats = alignments["round1_good"]
    order = [ALL[i] for i in (3, 0, 7, 5, 1, 6, 2, 4)]
    listed = _listed_in(stats, order, model.names)
    expected = centre_std_over_spacing(model, stats, SELECTED)
    got = centre_std_over_spacing(model, listed, SELECTED)
    assert got == pytest.approx(expected, rel=1e-12)
    # A list that does not name the model's views is unknown, not misattributed.
    wrong = _listed_in(stats, [*ALL[:-1], "other.png"], [*model.names[:-1], "other.png"])
    assert centre_std_over_spacing(model, wrong, SELECTED) is None
    # The handed-over alignment lists the restricted figures for the selected views, so round 3 reads
    # them for the right views too.
    prev_dir = _write_previous(tmp_path / "prev", model, listed)
    files = [tmp_path / "round2" / v for v in reversed(SELECTED)]
    res = _align_keeping_better_geometry(_FakeAlign(alignments["round2_poor"]), files, None, prev_dir, "never", "auto")
    assert res.decisions.geometry.used_previous
    assert res.decisions.geometry.previous_centre_std == pytest.approx(float(np.median(list(expected.values()))))
    ba = res.alignment.stats.bundle_adjustment
    assert ba.views == list(reversed(SELECTED)) and len(ba.centre_std_ratio) == len(SELECTED)
    res.write(tmp_path / "round2_align")
    handed = AlignStats.read(tmp_path / "round2_align" / "align.json")
    again = centre_std_over_spacing(res.alignment.sparse_model, handed, SELECTED)
    assert again == pytest.approx(expected, rel=1e-9)


def test_a_handed_over_alignment_keeps_the_previous_rounds_records(tmp_path, alignments):
    """Round 1's records (its photos, a calibration it inherited) travel with its alignment into round 2's
    align.json; only the geometry record is round 2's."""
    model, stats = alignments["round1_good"]
    photos = PhotosDecision("noisy", denoised_refused="the denoised photos were refused")
    n = len(model.points_xyz)
    prev_dir = tmp_path / "prev"
    AlignStageResult(AlignResult(model, model.points_xyz, model.points_rgb, np.full(n, 3.0), stats),
                     AlignDecisions(photos=photos)).write(prev_dir)
    np.savez(prev_dir / "points.npz", xyz=model.points_xyz, rgb=model.points_rgb, conf=np.full(n, 3.0))
    files = [tmp_path / "round2" / v for v in SELECTED]
    res = _align_keeping_better_geometry(_FakeAlign(alignments["round2_poor"]), files, None, prev_dir, "never", "auto")
    assert res.decisions.geometry.used_previous and res.decisions.photos == photos
    res.write(tmp_path / "round2_align")
    assert AlignDecisions.read(tmp_path / "round2_align" / "align.json") == res.decisions


@pytest.mark.parametrize("error", [DegenerateGeometryError("the views do not determine the cameras"),
                                   DisconnectedViewsError("the pair graph is disconnected: the views do not "
                                                          "determine the cameras"),
                                   AlignmentRefusedError("the positions of 1 of 5 views do not determine the "
                                                         "cameras", kind="positions_undetermined", views=("b.png",),
                                                         fix="pass --allow-partial")])
def test_align_stage_failure_falls_back_or_raises(tmp_path, alignments, error):
    """A round-2 alignment that fails on its geometry (refused, or its re-denoised photos no longer relate
    every view: measured on DTU scan24 at sigma 50) hands over the previous round's cameras."""
    prev_dir = _write_previous(tmp_path / "prev", *alignments["round1_good"])
    files = [tmp_path / "round2" / v for v in SELECTED]
    res = _align_keeping_better_geometry(_FakeAlign(error=error), files, None, prev_dir, "never", "auto")
    record = res.decisions.geometry
    assert record.used_previous and "do not determine" in record.current_error
    with pytest.raises(type(error)) as info:
        _align_keeping_better_geometry(_FakeAlign(error=error), files, None, prev_dir, "never", "never")
    assert "pass --allow-partial" not in str(info.value)  # the pipeline's fix (`as_pipeline_refusal`)
    with pytest.raises(type(error)):
        _align_keeping_better_geometry(_FakeAlign(error=error), [*files, tmp_path / "round2" / "new.png"], None,
                                       prev_dir, "never", "auto")


def test_an_input_error_is_not_a_geometry_to_fall_back_from(tmp_path, alignments):
    prev_dir = _write_previous(tmp_path / "prev", *alignments["round1_good"])
    files = [tmp_path / "round2" / v for v in SELECTED]
    with pytest.raises(InputError, match="identical"):
        _align_keeping_better_geometry(_FakeAlign(error=InputError("images a and b are identical")), files, None,
                                       prev_dir, "never", "auto")


def test_reuse_geometry_setting_is_validated():
    assert PipelineConfig().align.reuse_geometry == "auto"
    with pytest.raises(ConfigError, match="reuse_geometry"):
        PipelineConfig(align=AlignSettings(reuse_geometry="sometimes"))  # type: ignore[arg-type]


def test_reuse_geometry_reaches_later_rounds_only(tmp_path):
    scene = make_scene(tmp_path / "images", n=5)
    seen = []

    def stages():
        tiny = TinyStages()

        def align(ctx):
            seen.append((ctx.work_dir.parent.name, ctx.settings.reuse_geometry))
            return tiny.align(ctx)

        return tiny, dataclasses.replace(tiny.stages(), align=align)

    out, cfg = tmp_path / "out", preset("fast", views=3, rounds=2)
    run_pipeline(scene, out, cfg, stages=stages()[1])
    assert seen == [("round1", None), ("round2", "auto")]
    # The setting belongs to rounds >= 2: changing it re-runs round 2's alignment, never round 1's.
    seen.clear()
    tiny2, stages2 = stages()
    never = dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, reuse_geometry="never"))
    run_pipeline(scene, out, never, stages=stages2)
    assert seen == [("round2", "never")] and tiny2.calls["denoise"] == 0


def test_every_preset_takes_the_noisy_band_and_keeps_better_cameras():
    """The product's presets run one round and train the splat on the noisy photos' band instead of fusing
    (`fast`, N2V: band 0.5 against the fusion on the demo's scene and DTU scan24; round 2 lowered the
    held-out PSNR on DTU with Poisson-Gaussian noise, docs/bench/pipeline_demo.md); rounds >= 2 keep the
    better focal and poses; the paper's loop stays reachable by turning them off."""
    from eval.pipeline.config import PRESETS

    for name, cfg in PRESETS.items():
        n2v = cfg.denoise.method == "n2v"
        assert not cfg.fuse_noisy_splat and cfg.rounds == 1, name
        assert cfg.splat.noisy_detail == (0.5 if n2v else 0.2), name
        assert (cfg.align.reuse_intrinsics, cfg.align.reuse_geometry) == ("auto", "auto"), name
    assert [n for n, c in PRESETS.items() if c.denoise.method == "n2v"] == ["fast"]
    paper = dataclasses.replace(PRESETS["fast"], fuse_noisy_splat=False,
                                align=dataclasses.replace(PRESETS["fast"].align, reuse_intrinsics="never",
                                                          reuse_geometry="never"))
    assert not paper.fuse_noisy_splat and paper.align.reuse_geometry == "never"


class _PhotoAlign:
    """Stands in for `mvgeo.align.align_images` in round 1: one prepared alignment (or error) for the noisy
    photos (folder "noisy") and one for the denoised photos (folder "denoised"); records the calls."""

    def __init__(self, noisy, denoised):
        self.by_folder, self.calls = {"noisy": noisy, "denoised": denoised}, []

    def __call__(self, files, cfg, names=None, cloud_images=None):
        folder = files[0].parent.name
        self.calls.append((folder, cfg.pairwise.sensitive_below_noise,
                           None if cloud_images is None else cloud_images[0].parent.name))
        made = self.by_folder[folder]
        if isinstance(made, Exception):
            raise made
        model, stats = made
        return AlignResult(model, np.zeros((2, 3)), np.zeros((2, 3), np.uint8), np.ones(2), dataclasses.replace(stats))


def _round1_files(tmp_path):
    denoised = [tmp_path / "denoised" / v for v in ALL]
    noisy = {v.rsplit(".", 1)[0]: tmp_path / "noisy" / v for v in ALL}
    return denoised, noisy


@pytest.mark.parametrize(("noisy", "denoised", "kept"), [("round1_poor", "round1_good", "denoised"),
                                                         ("round1_good", "round1_poor", "noisy")])
def test_better_of_keeps_the_photos_whose_centres_are_better_determined(tmp_path, alignments, noisy, denoised,
                                                                        kept):
    """`AlignSettings.photos` "better_of": both alignments run and the one with the smaller bundle-adjustment
    centre uncertainty is kept; the ground truth confirms it is the closer one."""
    from eval.pipeline.align_stage import _align_first_round
    from mvgeo.align import AlignConfig

    files, noisy_files = _round1_files(tmp_path)
    fake = _PhotoAlign(alignments[noisy], alignments[denoised])
    res = _align_first_round(fake, files, noisy_files, AlignConfig(), keep_better=True)
    chosen = alignments[noisy if kept == "noisy" else denoised]
    assert res.alignment.sparse_model is chosen[0]
    other = alignments[denoised if kept == "noisy" else noisy]
    assert (_relative_rotation_error_deg(res.alignment.sparse_model, ALL)
            < _relative_rotation_error_deg(other[0], ALL))
    record = res.decisions.photos
    assert record.aligned == kept
    stds = record.comparison.centre_std_over_spacing
    assert stds.of(kept) < stds.of("denoised" if kept == "noisy" else "noisy")
    assert res.decisions.to_json()[PHOTOS_KEY]["aligned"] == kept  # align.json, as before
    # the noisy photos with the configured detector and the denoised cloud, the denoised photos with the
    # detector for noisy photos (`denoised_photos_config`)
    default = AlignConfig().pairwise.sensitive_below_noise
    assert fake.calls == [("noisy", default, "denoised"), ("denoised", 0.0, None)]


def test_better_of_with_one_refusal_keeps_the_other(tmp_path, alignments):
    from eval.pipeline.align_stage import _align_first_round
    from mvgeo.align import AlignConfig

    files, noisy_files = _round1_files(tmp_path)
    refused = AlignmentRefusedError("the positions of 1 of 8 views do not determine the cameras",
                                    kind="positions_undetermined", views=(ALL[3],), fix="pass --allow-partial")
    res = _align_first_round(_PhotoAlign(alignments["round1_poor"], refused), files, noisy_files, AlignConfig(),
                             keep_better=True)
    assert res.alignment.sparse_model is alignments["round1_poor"][0]
    assert res.decisions.photos.aligned == "noisy"
    assert "do not determine" in res.decisions.photos.denoised_refused
    res = _align_first_round(_PhotoAlign(refused, alignments["round1_poor"]), files, noisy_files, AlignConfig(),
                             keep_better=True)
    assert res.alignment.sparse_model is alignments["round1_poor"][0]
    assert res.decisions.photos == PhotosDecision("denoised", noisy_refused=str(refused).splitlines()[0])
    assert res.decisions.to_json()[PHOTOS_KEY] == {"aligned": "denoised",
                                                   "noisy_refused": str(refused).splitlines()[0]}
    # both refused: the denoised photos' refusal, with the pipeline's fix
    with pytest.raises(AlignmentRefusedError) as info:
        _align_first_round(_PhotoAlign(refused, refused), files, noisy_files, AlignConfig(), keep_better=True)
    assert "pass --allow-partial" not in str(info.value.fix)
    # "noisy_first" never aligns the denoised photos once the noisy ones align
    fake = _PhotoAlign(alignments["round1_poor"], alignments["round1_good"])
    res = _align_first_round(fake, files, noisy_files, AlignConfig(), keep_better=False)
    assert res.alignment.sparse_model is alignments["round1_poor"][0] and [c[0] for c in fake.calls] == ["noisy"]
    assert res.decisions.photos == PhotosDecision("noisy")


@pytest.mark.parametrize("keep_better", [True, False])
def test_photos_passed_through_are_aligned_once(tmp_path, alignments, keep_better):
    """Denoised photos that are the noisy ones (the denoise stage passed them through): one alignment, of the
    noisy photos with the configured detector, recorded as such. Where it is refused, the same pixels are
    tried with the detector for denoised photos; both refused, the refusal is raised with the pipeline's fix."""
    from eval.pipeline.align_stage import _align_first_round
    from mvgeo.align import AlignConfig

    files, noisy_files = _round1_files(tmp_path)
    fake = _PhotoAlign(alignments["round1_poor"], alignments["round1_good"])
    res = _align_first_round(fake, files, noisy_files, AlignConfig(), keep_better=keep_better, identical=True)
    assert res.alignment.sparse_model is alignments["round1_poor"][0]
    assert fake.calls == [("noisy", AlignConfig().pairwise.sensitive_below_noise, "denoised")]
    assert res.decisions.photos == PhotosDecision("noisy", identical=True)
    record = res.decisions.to_json()[PHOTOS_KEY]
    assert record == {"aligned": "noisy", "identical_photos": True}
    assert PhotosDecision.from_json(record) == res.decisions.photos
    assert "identical_photos" not in PhotosDecision("noisy").to_json()  # older records read alike
    refused = AlignmentRefusedError("the positions of 1 of 8 views do not determine the cameras",
                                    kind="positions_undetermined", views=(ALL[3],), fix="pass --allow-partial")
    fake = _PhotoAlign(refused, alignments["round1_good"])
    res = _align_first_round(fake, files, noisy_files, AlignConfig(), keep_better=keep_better, identical=True)
    assert res.alignment.sparse_model is alignments["round1_good"][0]
    assert [c[:2] for c in fake.calls] == [("noisy", AlignConfig().pairwise.sensitive_below_noise), ("denoised", 0.0)]
    assert res.decisions.photos == PhotosDecision("denoised", noisy_refused=str(refused).splitlines()[0],
                                                  identical=True)
    with pytest.raises(AlignmentRefusedError) as info:
        _align_first_round(_PhotoAlign(refused, refused), files, noisy_files, AlignConfig(), keep_better=keep_better,
                           identical=True)
    assert "pass --allow-partial" not in str(info.value.fix)


def test_same_photos_compares_pixels(tmp_path):
    """`same_photos`: equal pixels count as the same photo whatever the file's bytes; one differing pixel, a
    missing noisy photo or another size does not."""
    from eval.pipeline.align_stage import same_photos
    from mvgeo.common.imageio import write_image

    rng = np.random.default_rng(0)
    ims = {f"v{i}": rng.integers(0, 256, (12, 16, 3)).astype(np.float32) / 255.0 for i in range(3)}
    for folder in ("denoised", "noisy"):
        (tmp_path / folder).mkdir()
        for stem, im in ims.items():
            write_image(tmp_path / folder / f"{stem}.png", im)
    files = sorted((tmp_path / "denoised").glob("*.png"))
    noisy = {p.stem: p for p in (tmp_path / "noisy").glob("*.png")}
    assert same_photos(files, noisy)
    # the same pixels in another encoding (PNG compression level): still the same photos
    import cv2

    bgr = np.round(255.0 * ims["v1"][:, :, ::-1]).astype(np.uint8)
    cv2.imwrite(str(noisy["v1"]), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 0])
    assert noisy["v1"].read_bytes() != files[1].read_bytes() and same_photos(files, noisy)
    changed = ims["v2"].copy()
    changed[5, 7, 1] = (round(255 * changed[5, 7, 1]) ^ 1) / 255.0
    write_image(noisy["v2"], changed)
    assert not same_photos(files, noisy)
    write_image(noisy["v2"], ims["v2"])
    assert same_photos(files, noisy)
    assert not same_photos(files, {k: v for k, v in noisy.items() if k != "v0"})
    write_image(noisy["v0"], ims["v0"][:, :8])
    assert not same_photos(files, noisy)
    noisy["v0"].write_bytes(b"not a photo")
    assert not same_photos(files, noisy)


def test_better_of_without_a_known_uncertainty_keeps_the_noisy_photos(alignments):
    from eval.pipeline.calibration import better_determined

    good_model, good_stats = alignments["round1_good"]
    poor_model, poor_stats = alignments["round1_poor"]
    unknown = dataclasses.replace(good_stats, bundle_adjustment=None)
    keep, record = better_determined(good_model, unknown, poor_model, poor_stats, ALL)
    assert not keep and record.centre_std_over_spacing.denoised is None
    keep, _ = better_determined(good_model, good_stats, poor_model, poor_stats, ALL)
    assert keep
    # fewer registered views lose whatever their uncertainty
    fewer = SparseModel(good_model.cameras, [good_model.image(v) for v in ALL[:-1]], good_model.points_xyz,
                        good_model.points_rgb)
    keep, record = better_determined(fewer, good_stats, poor_model, poor_stats, ALL)
    assert not keep and record.registered == PerPhotos(denoised=7, noisy=8)
