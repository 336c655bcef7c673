"""`evaluate_dataset` / `run_task` with the small real stages of the pipeline tests in place of the
product's (`eval.methods.product_stages` patched) and a recording scorer: which folders and files a
method writes, which errors become "failed" rows, and the ground-truth-pose baseline's splat stage."""

from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np
import pytest

import eval.evaluate
import eval.methods
from eval.evaluate import EvalConfig, EvalTask, evaluate_dataset, run_task
from eval.methods import METHODS
from eval.pipeline import preset
from eval.pipeline.validate import DatasetFolder
from mvgeo.camera import Camera
from mvgeo.common.errors import AlignmentRefusedError, DegenerateGeometryError, InputError
from mvgeo.sparse_model import read_sparse_model
from tests.eval._tiny_stages import TinyStages, make_scene, tiny_dataset


@pytest.fixture()
def dataset(tmp_path) -> DatasetFolder:
    return tiny_dataset(tmp_path / "data")


class Harness:
    """Tiny stages in place of the product's, and a scorer that records what it was given."""

    def __init__(self, monkeypatch):
        self.tiny = TinyStages()
        self.scored: list[dict] = []
        self.splat_settings: list = []
        monkeypatch.setattr(eval.methods, "product_stages", self.stages)
        monkeypatch.setattr(eval.evaluate, "read_gaussian_ply", lambda path, device: path)
        monkeypatch.setattr(eval.evaluate, "_score_scene", self.score)

    def stages(self):
        def splat(ctx):
            self.splat_settings.append(ctx.settings)
            return self.tiny.splat(ctx)

        return dataclasses.replace(self.tiny.stages(), splat=splat)

    def score(self, model, gt, est_train, dataset, config, est_cameras=(), renders_out=None):
        self.scored.append({"ply": model, "est": est_train, "cams": list(est_cameras)})
        if renders_out is not None:
            renders_out.update({n: np.full((40, 48, 3), 0.5, np.float32) for n in dataset.test})
        return {n: {"psnr_db": 20.0, "ssim": 0.5, "lpips": 0.3} for n in dataset.test}, \
            {"rot_err_deg": 1.0, "ate": 0.1}


def _task(dataset, tmp_path, name, seed=0, **config) -> EvalTask:
    cfg = EvalConfig(methods=(name,), seeds=1, preset="fast", **config)
    base = preset("fast", views=3)
    inputs = eval.evaluate.copy_train_inputs(dataset, tmp_path / "out" / "inputs" / "s")
    return EvalTask("s", METHODS[name], seed, dataset, base, inputs, tmp_path / "out", cfg)


def test_baselines_write_no_model_file(tmp_path, dataset, monkeypatch):
    """No fake outputs: a denoiser without a network leaves no `n2v_model.pt` in its run folder."""
    h = Harness(monkeypatch)
    runs = tmp_path / "out" / "runs" / "s" / "seed0"
    for name in ("instantsplat", "n2v_round1"):
        row = run_task(_task(dataset, tmp_path, name))
        assert row.method == name and not row.error and row.psnr_db == 20.0
    assert (runs / "instantsplat" / "round1" / "denoised").is_dir()
    assert not list((runs / "instantsplat").rglob("n2v_model.pt"))
    assert (runs / "n2v" / "round1" / "n2v_model.pt").is_file()  # the N2V method's network
    assert h.tiny.calls["denoise"] == 1  # instantsplat's denoise stage is the identity, not the tiny one
    assert all(s["est"] is not None for s in h.scored)  # pose-free: estimated poses are registered


def test_gt_poses_baseline_runs_the_pipeline_splat_stage(tmp_path, dataset, monkeypatch):
    h = Harness(monkeypatch)
    row = run_task(_task(dataset, tmp_path, "3dgs_gt_poses"))
    assert row.method == "3dgs_gt_poses" and not row.error
    rd = tmp_path / "out" / "runs" / "s" / "seed0" / "3dgs_gt_poses" / "round1"
    # The splat stage the pipeline uses, with the ground-truth cameras and the known-pose preset.
    assert h.tiny.calls["splat"] == 1 and h.tiny.calls["align"] == 0
    (settings,) = h.splat_settings
    assert settings.train.optimize_poses is False
    aligned = read_sparse_model(rd / "align" / "sparse" / "0")
    gt = read_sparse_model(dataset.root / "sparse" / "0")
    assert [n.rsplit(".", 1)[0] for n in aligned.names] == dataset.train
    for n in aligned.names:
        np.testing.assert_allclose(aligned.image(n).cam_from_world, gt.image(n).cam_from_world, atol=1e-12)
    np.testing.assert_allclose(np.load(rd / "align" / "points.npz")["xyz"], gt.points_xyz)
    assert h.scored[0]["est"] is None and h.scored[0]["ply"] == rd / "point_cloud.ply"
    # Resumable like the pipeline: a second run reuses both stages.
    run_task(_task(dataset, tmp_path, "3dgs_gt_poses"))
    assert h.tiny.calls["splat"] == 1


def test_a_gt_pose_variant_splats_its_methods_photos_with_the_true_cameras(tmp_path, dataset, monkeypatch):
    h = Harness(monkeypatch)
    row = run_task(_task(dataset, tmp_path, "n2v_round1@gt_poses"))
    assert row.method == "n2v_round1@gt_poses" and not row.error
    seed_dir = tmp_path / "out" / "runs" / "s" / "seed0"
    own, rd = seed_dir / "n2v" / "round1", seed_dir / "n2v@gt_poses" / "round1"
    # Its method and oracle_clean (the points) ran first (their own splats with pose learning), then one more
    # splat: known poses, the method's denoised photos, ground-truth cameras.
    assert h.tiny.calls["align"] == 2 and h.tiny.calls["splat"] == 3
    assert [s.train.optimize_poses for s in h.splat_settings] == [True, True, False]
    assert (own / "point_cloud.ply").is_file() and (rd / "point_cloud.ply").is_file()
    aligned = read_sparse_model(rd / "align" / "sparse" / "0")
    gt = read_sparse_model(dataset.root / "sparse" / "0")
    for n in aligned.names:
        np.testing.assert_allclose(aligned.image(n).cam_from_world, gt.image(n).cam_from_world, atol=1e-12)
    # Initial points: oracle_clean's alignment points on the true cameras' rays. The tiny alignment puts the
    # training cameras at x = 0.1 i (i = 0..4), the ground truth at 0.1 (i + 1) with the same intrinsics: each
    # point its cameras see moves by 0.1 along x; the ones none of them sees are dropped.
    est_xyz = np.load(seed_dir / "oracle_clean" / "round1" / "align" / "points.npz")["xyz"]
    placed = np.load(rd / "align" / "points.npz")["xyz"]
    expected = est_xyz + [0.1, 0.0, 0.0]
    assert 10 <= len(placed) <= len(est_xyz)
    assert all(np.min(np.abs(expected - p).max(axis=1)) < 1e-9 for p in placed)
    assert h.scored[-1]["est"] is None and h.scored[-1]["ply"] == rd / "point_cloud.ply"  # scored at the true poses
    run_task(_task(dataset, tmp_path, "n2v_round1@gt_poses"))  # resumable: nothing runs again
    assert h.tiny.calls["splat"] == 3 and h.tiny.calls["align"] == 2


def _refuse_but_the_oracle(h, monkeypatch):
    """Every alignment but oracle_clean's refuses its photos (as the temple ring's at sigma 25 do)."""
    tiny_align = h.tiny.align

    def align(ctx):
        if "oracle_clean" not in str(ctx.work_dir):
            raise AlignmentRefusedError("the reconstruction is inconsistent with 2 of 3 verified image pairs",
                                        kind="pairs_contradicted")
        return tiny_align(ctx)

    monkeypatch.setattr(h.tiny, "align", align)


def test_a_gt_pose_variant_splats_the_denoised_photos_its_method_could_not_align(tmp_path, dataset, monkeypatch):
    # The method's alignment refuses its photos (as the temple ring at sigma 25 does): the method's row fails,
    # its variant still splats round 1's denoised photos with the true cameras from oracle_clean's points.
    h = Harness(monkeypatch)
    _refuse_but_the_oracle(h, monkeypatch)
    assert run_task(_task(dataset, tmp_path, "n2v_round1")).error.startswith("AlignmentRefusedError")
    row = run_task(_task(dataset, tmp_path, "n2v_round1@gt_poses"))
    assert row.method == "n2v_round1@gt_poses" and not row.error
    seed_dir = tmp_path / "out" / "runs" / "s" / "seed0"
    own, rd = seed_dir / "n2v" / "round1", seed_dir / "n2v@gt_poses" / "round1"
    assert not (own / "point_cloud.ply").exists() and (rd / "point_cloud.ply").is_file()
    assert h.tiny.calls["denoise"] == 1  # round 1's denoised photos, from the stage cache
    assert [s.train.optimize_poses for s in h.splat_settings] == [True, False]  # oracle_clean's, the variant's
    assert h.scored[-1]["est"] is None and h.scored[-1]["ply"] == rd / "point_cloud.ply"


def test_a_gt_pose_variant_after_a_refusal_does_not_depend_on_an_earlier_runs_records(tmp_path, dataset,
                                                                                       monkeypatch):
    # An earlier evaluation into the folder aligned and splatted round 1 (its splat record stays); with other
    # denoiser settings the method's alignment now refuses. The variant splats round 1's new denoised photos,
    # as it does in a new folder, instead of failing on the earlier run's splat record.
    h = Harness(monkeypatch)
    assert not run_task(_task(dataset, tmp_path, "n2v_round1@gt_poses")).error
    _refuse_but_the_oracle(h, monkeypatch)
    task = _task(dataset, tmp_path, "n2v_round1@gt_poses")
    task = dataclasses.replace(task, base=dataclasses.replace(
        task.base, denoise=dataclasses.replace(task.base.denoise, n2v_steps=7)))
    row = run_task(task)
    assert not row.error and row.psnr_db == 20.0
    assert h.tiny.calls["denoise"] == 2  # round 1 denoised again with the new settings, then splatted


def test_a_gt_pose_variant_splats_the_photos_its_method_trained_on_now(tmp_path, dataset, monkeypatch):
    # An earlier evaluation into the folder ran `product` with a preset that fused (its fused/ stays in the
    # round folder); now the preset does not fuse and `product` trains on denoised/: so does its variant.
    h = Harness(monkeypatch)
    task = _task(dataset, tmp_path, "product@gt_poses")
    assert not run_task(dataclasses.replace(task, base=dataclasses.replace(task.base, fuse_noisy_splat=True))).error
    seed_dir = tmp_path / "out" / "runs" / "s" / "seed0"
    assert (seed_dir / "product" / "round1" / "fused").is_dir()
    read: list = []
    tiny_splat = h.tiny.splat

    def splat(ctx):
        read.append((ctx.work_dir.parent.parent.name, ctx.inputs["images"].name))
        return tiny_splat(ctx)

    monkeypatch.setattr(h.tiny, "splat", splat)
    assert not run_task(task).error
    assert read == [("product", "denoised"), ("product@gt_poses", "denoised")]


def _ring_of_cameras(rng, est_from_ref, n=5):
    """n reference cameras looking down +z at the points near z = 5, and the same cameras in the estimated
    world x_est = s R x_ref + t: R_e = R R_s^T, t_e = s t - R_e t_s."""
    from mvgeo.sparse_model import PosedImage
    from mvgeo.transforms import R_from_axis_angle

    ref, est = [], []
    for i in range(n):
        R = R_from_axis_angle(0.05 * rng.normal(size=3))
        t = np.array([0.3 * rng.normal(), 0.3 * rng.normal(), 0.1 * rng.normal()])
        ref.append(PosedImage(f"v{i}.png", 1, np.hstack([R, t[:, None]])))
        R_e = R @ est_from_ref.R.T
        t_e = est_from_ref.scale * t - R_e @ est_from_ref.t
        est.append(PosedImage(f"v{i}.png", 1, np.hstack([R_e, t_e[:, None]])))
    return ref, est


def test_points_go_on_the_true_cameras_rays(tmp_path):
    from eval.baselines import points_in_reference_frame
    from mvgeo.sparse_model import SparseModel, write_sparse_model
    from mvgeo.transforms import R_from_axis_angle, Sim3

    rng = np.random.default_rng(3)
    est_from_ref = Sim3(2.5, R_from_axis_angle(rng.normal(size=3)), rng.normal(size=3))
    ref_images, est_images = _ring_of_cameras(rng, est_from_ref)
    cam = Camera("PINHOLE", 40, 30, [30.0, 30.0, 20.0, 15.0])
    xyz_ref = rng.normal(size=(60, 3)) * [1.5, 1.2, 0.5] + [0.0, 0.0, 5.0]
    views = tuple(f"v{i}" for i in range(5))
    # 1. exact data (the estimate is the reference up to a similarity): every seen point comes back exactly
    write_sparse_model(tmp_path / "est", SparseModel({1: cam}, est_images), binary=True)
    np.savez(tmp_path / "points.npz", xyz=est_from_ref.apply(xyz_ref), rgb=np.arange(180).reshape(60, 3) % 255)
    ref = SparseModel({1: cam}, ref_images)
    xyz, rgb = points_in_reference_frame(tmp_path / "est", tmp_path / "points.npz", ref, views)
    seen = np.zeros(60, bool)
    for im in ref_images:
        p = xyz_ref @ im.cam_from_world[:, :3].T + im.cam_from_world[:, 3]
        seen |= cam.in_image(cam.project(p).uv_px) & (p[:, 2] > 0)
    assert 20 <= seen.sum() < 60 and len(xyz) == seen.sum()  # points no camera sees are dropped
    np.testing.assert_allclose(xyz, xyz_ref[seen], atol=1e-9)  # only rounding
    np.testing.assert_array_equal(rgb, (np.arange(180).reshape(60, 3) % 255)[seen])
    # 2. an estimate with a focal 5 % off: each point still lands on the true ray of the pixel where the
    # estimate's nearest camera saw it
    cam_wrong = Camera("PINHOLE", 40, 30, [31.5, 31.5, 20.0, 15.0])
    write_sparse_model(tmp_path / "est2", SparseModel({1: cam_wrong}, est_images), binary=True)
    xyz2, _ = points_in_reference_frame(tmp_path / "est2", tmp_path / "points.npz", ref, views)
    assert len(xyz2) > 0
    for q in xyz2:
        hits = []
        for im_e, im_r in zip(est_images, ref_images, strict=True):
            p_e = est_from_ref.apply(xyz_ref) @ im_e.cam_from_world[:, :3].T + im_e.cam_from_world[:, 3]
            uv_e = cam_wrong.project(p_e).uv_px
            q_r = q @ im_r.cam_from_world[:, :3].T + im_r.cam_from_world[:, 3]
            hits.append(np.min(np.linalg.norm(uv_e - cam.project(q_r[None]).uv_px, axis=1)))
        assert min(hits) < 1e-6  # on the ray through a pixel where the estimate's camera saw a point


def test_degenerate_geometry_becomes_a_failed_row(tmp_path, dataset, monkeypatch):
    h = Harness(monkeypatch)

    def align(ctx):
        raise DegenerateGeometryError("the focal length is not determined by these views")

    monkeypatch.setattr(h.tiny, "align", align)
    seen = []
    rows = evaluate_dataset(dataset, tmp_path / "out", EvalConfig(methods=("3dgs_gt_poses", "instantsplat"), seeds=1,
                                                                  preset="fast"),
                            scene="s", on_row=lambda rs: seen.append(len(rs)))
    assert [r.method for r in rows] == ["3dgs_gt_poses", "instantsplat"] and seen == [1, 2]
    ok, failed = rows
    assert not ok.error and ok.psnr_db == 20.0  # the other method's row is kept
    assert failed.error.startswith("DegenerateGeometryError: the focal length")
    assert all(math.isnan(v) for v in (failed.psnr_db, failed.ssim, failed.lpips))


def test_first_seed_runs_those_seeds_only(tmp_path, dataset, monkeypatch):
    """`--first-seed 2 --seeds 2`: seeds 2 and 3, each in its own seed folder, seed 0's folder never made."""
    Harness(monkeypatch)
    out = tmp_path / "out"
    rows = evaluate_dataset(dataset, out, EvalConfig(methods=("instantsplat",), seeds=2, first_seed=2, preset="fast"),
                            scene="s")
    assert [(r.method, r.seed) for r in rows] == [("instantsplat", 2), ("instantsplat", 3)]
    assert sorted(p.name for p in (out / "runs" / "s").iterdir()) == ["seed2", "seed3"]
    assert list(EvalConfig(seeds=3, first_seed=1).seed_values) == [1, 2, 3]
    with pytest.raises(InputError, match="--first-seed"):
        EvalConfig(first_seed=-1)


@pytest.mark.parametrize("error", [TypeError("bad argument"), RuntimeError("boom"), ValueError("shape"),
                                   KeyError("views")])
def test_programming_errors_surface(tmp_path, dataset, monkeypatch, error):
    h = Harness(monkeypatch)

    def align(ctx):
        raise error

    monkeypatch.setattr(h.tiny, "align", align)
    rows = []
    with pytest.raises(type(error)):
        evaluate_dataset(dataset, tmp_path / "out", EvalConfig(methods=("instantsplat",), seeds=1, preset="fast"),
                         scene="s", on_row=rows.append)
    assert rows == []  # no "failed" row hides it


def test_a_task_pickles(tmp_path, dataset):
    task = _task(dataset, tmp_path, "denoise_gs_fused", seed=2)
    again = pickle.loads(pickle.dumps(task))
    assert again == task and again.method.pipeline_config(again.base) == task.method.pipeline_config(task.base)


def test_a_denoiser_without_a_network_cannot_start_round_2(tmp_path):
    from eval.baselines import CLASSICAL_DENOISE_OUTPUTS, identity_denoise
    from eval.pipeline import run_pipeline

    scene = make_scene(tmp_path / "images", n=4)
    tiny = TinyStages()
    stages = dataclasses.replace(tiny.stages(), denoise=identity_denoise, denoise_outputs=CLASSICAL_DENOISE_OUTPUTS)
    with pytest.raises(ValueError, match="n2v_model.pt"):
        run_pipeline(scene, tmp_path / "out", preset("fast", views=3, rounds=2), stages=stages)
    assert not (tmp_path / "out").exists() and not tiny.calls
