"""Rounds >= 2 reuse the previous round's noisy-photo splat renders (`PipelineConfig.reuse_noisy_splat`):
the decision (`eval.pipeline.fuse_stage.noisy_splat_reuse`) against hand-built alignments, and the real fuse
stage in a two-round pipeline whose round 2 is handed round 1's alignment, or not."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from eval.pipeline import SplatSettings, preset, run_pipeline
from eval.pipeline.fuse_stage import ROTATION_ATOL, fuse, fuse_images, noisy_splat_reuse
from eval.pipeline.stage_settings import round_settings
from eval.pipeline.views import read_views, write_views
from mvgeo.camera import Camera
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model
from tests.eval._tiny_stages import TinyStages, make_scene

VIEWS = ["view_000", "view_001", "view_002", "view_003"]

#: Half a 16-bit PNG step: `write_views` rounds each value to the nearest multiple of 1/65535.
PNG16_HALF_STEP = 0.5 / 65535


def _rot_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _write_align(folder, views, *, fx=50.0, tilt_rad=None, seed=0):
    """An align stage folder: PINHOLE 48x40, view i at x = 0.1 i, turned by 0.05 i rad about z (plus
    `tilt_rad[view]`), 20 points from `seed`."""
    tilt_rad = tilt_rad or {}
    images = []
    for i, v in enumerate(views):
        R = _rot_z(0.05 * i + tilt_rad.get(v, 0.0))
        images.append(PosedImage(f"{v}.png", 1, np.hstack([R, [[-0.1 * i], [0.0], [0.0]]])))
    rng = np.random.default_rng(seed)
    xyz, rgb = rng.normal(size=(20, 3)) + [0, 0, 4], (rng.random((20, 3)) * 255).astype(np.uint8)
    model = SparseModel({1: Camera("PINHOLE", 48, 40, [fx, fx, 24.0, 20.0])}, images, xyz, rgb)
    write_sparse_model(folder / "sparse" / "0", model, binary=True)
    np.savez(folder / "points.npz", xyz=xyz, rgb=rgb, conf=np.ones(len(xyz)))
    return folder


def _handed_over(previous, folder, views):
    """What the align stage writes when it hands the previous round's geometry over: the previous sparse
    model restricted to `views` (written again, so rotations go through one more quaternion round
    trip) and its points."""
    model = read_sparse_model(previous / "sparse" / "0")
    images = [model.image(f"{v}.png") for v in views]
    write_sparse_model(folder / "sparse" / "0", SparseModel(model.cameras, images, model.points_xyz,
                                                            model.points_rgb), binary=True)
    shutil.copyfile(previous / "points.npz", folder / "points.npz")
    return folder


@pytest.fixture
def rounds(tmp_path):
    """(previous align, previous noisy, previous renders, noisy) folders for the decision tests."""
    noisy = make_scene(tmp_path / "noisy", n=4)
    prev_align = _write_align(tmp_path / "prev_align", VIEWS)
    renders = tmp_path / "renders"
    write_views(renders, {v: np.full((40, 48, 3), 0.25 * k, np.float32) for k, v in enumerate(VIEWS)})
    return prev_align, noisy, renders


def _decide(tmp_path, rounds, align, views=("view_001", "view_003"), noisy=None):
    prev_align, prev_noisy, renders = rounds
    return noisy_splat_reuse(list(views), align_dir=align, previous_align_dir=prev_align,
                             noisy_dir=prev_noisy if noisy is None else noisy, previous_noisy_dir=prev_noisy,
                             previous_renders_dir=renders)


def test_reuse_when_the_alignment_is_handed_over(tmp_path, rounds):
    views = ["view_001", "view_003"]
    align = _handed_over(rounds[0], tmp_path / "align", views)
    # The handed-over rotations are not bit-identical (quaternion round trip), only within the tolerance.
    before, after = read_sparse_model(rounds[0] / "sparse" / "0"), read_sparse_model(align / "sparse" / "0")
    diffs = [np.abs(before.image(f"{v}.png").cam_from_world - after.image(f"{v}.png").cam_from_world).max()
             for v in views]
    assert max(diffs) <= ROTATION_ATOL
    decision = _decide(tmp_path, rounds, align, views)
    assert decision.reused, decision.reason


@pytest.mark.parametrize(("change", "reason"), [
    ("rotation", "cam_from_world of view_003"),
    ("translation", "cam_from_world of view_001"),
    ("intrinsics", "intrinsics of view_001"),
    ("points", "points differ"),
    ("noisy", "noisy photo view_001"),
    ("unrendered view", "no noisy-photo render"),
])
def test_no_reuse_when_an_input_of_the_splat_differs(tmp_path, rounds, change, reason):
    views = ["view_001", "view_003"]
    noisy = None
    if change == "rotation":  # 1e-9 rad: far below any pose estimate's accuracy, still not a copy
        align = _write_align(tmp_path / "align", VIEWS, tilt_rad={"view_003": 1e-9})
    elif change == "translation":
        align = _handed_over(rounds[0], tmp_path / "align", views)
        model = read_sparse_model(align / "sparse" / "0")
        im = model.image("view_001.png")
        cfw = im.cam_from_world.copy()
        cfw[0, 3] = np.nextafter(cfw[0, 3], 1.0)  # one ulp
        images = [PosedImage(im.name, im.camera_id, cfw), model.image("view_003.png")]
        write_sparse_model(align / "sparse" / "0", dataclasses.replace(model, images=images), binary=True)
    elif change == "intrinsics":
        align = _write_align(tmp_path / "align", VIEWS, fx=50.0 + 1e-9)
    elif change == "points":
        align = _write_align(tmp_path / "align", VIEWS, seed=1)
    elif change == "noisy":
        align = _handed_over(rounds[0], tmp_path / "align", views)
        noisy = tmp_path / "noisy2"
        shutil.copytree(rounds[1], noisy)
        img = read_views(noisy, ["view_001"])["view_001"]
        write_views(noisy, {"view_001": np.clip(img + 0.01, 0, 1)})
    else:
        align = _handed_over(rounds[0], tmp_path / "align", views)
        (rounds[2] / "view_003.png").unlink()
    decision = _decide(tmp_path, rounds, align, views, noisy=noisy)
    assert not decision.reused and reason in decision.reason


def _handover_align(tiny: TinyStages, *, perturb: bool = False):
    """Round 1: `TinyStages.align`. Rounds >= 2 with `reuse_geometry="auto"`: the previous round's
    alignment of this round's views (what the product's align stage writes when it keeps it), with one
    pose turned by 1e-6 rad when `perturb`; with "never": a new alignment (`TinyStages.align`)."""

    def align(ctx):
        previous = ctx.inputs.get("previous_align")
        if previous is None or ctx.settings.reuse_geometry == "never":
            return tiny.align(ctx)
        tiny.calls["align"] += 1
        views = sorted(p.stem for p in ctx.inputs["images"].glob("*.png"))
        out = _handed_over(previous, ctx.work_dir / "align", views)
        if perturb:
            model = read_sparse_model(out / "sparse" / "0")
            im = model.images[0]
            cfw = np.hstack([_rot_z(1e-6) @ im.cam_from_world[:, :3], im.cam_from_world[:, 3:]])
            images = [PosedImage(im.name, im.camera_id, cfw), *model.images[1:]]
            write_sparse_model(out / "sparse" / "0", dataclasses.replace(model, images=images), binary=True)
        return {"registered": len(views)}

    return align


@pytest.fixture
def trainings(monkeypatch):
    """Counts the splat trainings (`splat.train.train_gaussians` calls) of the real fuse stage."""
    import splat.train

    calls = []
    real = splat.train.train_gaussians

    def counting(*args, **kwargs):
        calls.append(len(args[0]))
        return real(*args, **kwargs)

    monkeypatch.setattr(splat.train, "train_gaussians", counting)
    return calls


def _run(tmp_path, name, *, reuse=True, geometry="auto", perturb=False, scene=None):
    scene = scene or make_scene(tmp_path / "images", n=5)
    tiny = TinyStages()
    stages = dataclasses.replace(tiny.stages(), fuse=fuse, align=_handover_align(tiny, perturb=perturb))
    cfg = preset("fast", views=3, rounds=2)
    cfg = dataclasses.replace(cfg, fuse_noisy_splat=True, reuse_noisy_splat=reuse,
                              align=dataclasses.replace(cfg.align, reuse_geometry=geometry),
                              splat=SplatSettings(preset="quick", iters=3))
    return run_pipeline(scene, tmp_path / name, cfg, stages=stages), cfg, scene


def test_round2_reuses_round1_noisy_renders(tmp_path, trainings):
    res, _, _ = _run(tmp_path, "on")
    r1, r2 = res.rounds
    summary = r2.stages["fuse"].summary
    assert summary["noisy_splat"] == "reused", summary["noisy_splat_reason"]
    assert r1.stages["fuse"].summary["noisy_splat"] == "trained"
    assert trainings == [5]  # round 1's splat of the 5 noisy photos only
    views = summary["views"]
    assert len(views) == 3 and set(views) < set(r1.stages["fuse"].summary["views"])
    for v in views:  # the previous round's render files, byte for byte
        assert (r2.dir / "noisy_renders" / f"{v}.png").read_bytes() == \
            (r1.dir / "noisy_renders" / f"{v}.png").read_bytes()
    denoised = read_views(r2.dir / "denoised", views)
    previous = read_views(r1.dir / "noisy_renders", views)
    fused = read_views(r2.dir / "fused", views)
    for v in views:
        expected = 0.5 * denoised[v].astype(np.float64) + 0.5 * previous[v].astype(np.float64)
        # `fuse_images` in float32, then the 16-bit PNG: within half a step (plus float32 rounding).
        np.testing.assert_allclose(fused[v], expected, rtol=0, atol=PNG16_HALF_STEP + 1e-7)
        np.testing.assert_allclose(fused[v], fuse_images(denoised[v], previous[v]), rtol=0,
                                   atol=PNG16_HALF_STEP + 1e-7)


def test_no_reuse_when_round2_aligns_anew_or_the_pose_moved(tmp_path, trainings):
    res, _, scene = _run(tmp_path, "never", geometry="never")
    summary = res.rounds[1].stages["fuse"].summary
    assert summary["noisy_splat"] == "trained" and "differ" in summary["noisy_splat_reason"]
    assert trainings == [5, 3]
    trainings.clear()
    res, _, _ = _run(tmp_path, "moved", perturb=True, scene=scene)
    summary = res.rounds[1].stages["fuse"].summary
    assert summary["noisy_splat"] == "trained" and "cam_from_world" in summary["noisy_splat_reason"]
    assert trainings == [5, 3]


def test_setting_off_trains_and_changing_it_reruns_round2_fuse_only(tmp_path, trainings):
    res, cfg, scene = _run(tmp_path, "out", reuse=False)
    summary = res.rounds[1].stages["fuse"].summary
    assert summary == {**summary, "noisy_splat": "trained", "noisy_splat_reason": "reuse_noisy_splat is off"}
    assert trainings == [5, 3]
    # Round 1's key ignores the setting, round 2's fuse key holds it: switching it on in the same folder
    # keeps round 1 and re-runs round 2's fuse, now reused.
    trainings.clear()
    res, _, _ = _run(tmp_path, "out", reuse=True, scene=scene)
    assert all(s.skipped for s in res.rounds[0].stages.values())
    assert not res.rounds[1].stages["fuse"].skipped and res.rounds[1].stages["select"].skipped
    assert res.rounds[1].stages["fuse"].summary["noisy_splat"] == "reused" and trainings == []
    # Resumed with the same settings: nothing runs.
    res, _, _ = _run(tmp_path, "out", reuse=True, scene=scene)
    assert all(s.skipped for r in res.rounds for s in r.stages.values())


def test_fuse_settings_hold_the_setting_in_later_rounds_only():
    cfg = dataclasses.replace(preset("fast", rounds=3), fuse_noisy_splat=True)
    assert cfg.reuse_noisy_splat
    assert round_settings(cfg, 1).fuse.reuse_noisy_splat is None
    assert round_settings(cfg, 2).fuse.reuse_noisy_splat is True
    off = dataclasses.replace(cfg, reuse_noisy_splat=False)
    assert round_settings(off, 3).fuse.reuse_noisy_splat is False
    assert round_settings(off, 1) == round_settings(cfg, 1)


def test_zero_passes_is_a_valid_setting_and_negative_is_refused():
    from eval.pipeline import DenoiseSettings
    from mvgeo.common.errors import ConfigError

    cfg = dataclasses.replace(preset("fast"), denoise=DenoiseSettings(n2v_preset="fast", passes=0))
    assert round_settings(cfg, 1).denoise.passes == 0 and round_settings(cfg, 2).refine.passes == 0
    with pytest.raises(ConfigError, match="denoise.passes"):
        dataclasses.replace(cfg, denoise=DenoiseSettings(passes=-1))
