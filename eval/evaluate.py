"""`denoise-gs eval`: methods side by side on a dataset with ground truth.

Protocol (issue 8):

- every method sees only the noisy images of the training split (copied into
  `OUT/inputs/<scene>/`); held-out views and clean images are used for scoring;
- pose-free methods are registered to ground truth as InstantSplat does: Sim(3)
  from the estimated to the true training cameras (`eval.heldout`), the true
  held-out cameras mapped in (relative to the nearest training camera, with the
  Sim(3) scale: `map_cameras_local`, because a reconstruction with a wrong focal
  length is distorted and no single Sim(3) fits it), rendered with the
  reconstruction's own intrinsics (`heldout_camera`), each refined
  photometrically with the Gaussians frozen (`splat.pose_fit.fit_pose`, against the *noisy* held-out image: the
  clean images serve scoring only), then rendered;
- held-out renders are scored against the clean images (PSNR, SSIM, LPIPS),
  training poses against ground truth (`mvgeo.metrics.compare_poses`).

Methods that share settings share a pipeline folder, so `n2v_round1`,
`denoise_gs` and `rounds_N` reuse each other's completed rounds (the stage
keys match). The dataset (noise realisation) is the same for every seed; the
seed drives the methods' own randomness.

Method (a) `3dgs_gt_poses` trains on the noisy training images with the
ground-truth poses, initialised from the ground-truth depth maps (an oracle
initialisation, so it is an optimistic baseline) or, without depth maps, from
the ground-truth model's points.

`oracle_clean` is a reference, not a competitor: (b)'s alignment and splat on the
*clean* training photos, i.e. a perfect denoiser. It is the ceiling of every
denoise-then-reconstruct method with the same settings.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from denoise.noise_level import estimate_noise_sigma
from eval.heldout import map_cameras_local
from eval.image_metrics import score_images
from eval.pipeline import PipelineConfig, StageContext, preset, product_stages, run_pipeline
from eval.pipeline.components import require
from eval.pipeline.config import DENOISE_METHODS, DenoiseMethod
from eval.pipeline.stages import check_product_components
from eval.pipeline.validate import DatasetFolder
from eval.pipeline.views import read_views, write_views
from eval.results import RunScores
from mvgeo.camera import Camera
from mvgeo.common.deps import cv2
from mvgeo.common.errors import DgsError, InputError
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import SparseModel, read_sparse_model

__all__ = ["EVAL_METHODS", "EvalConfig", "evaluate_dataset", "method_pipeline_config", "scene_dataset",
           "score_reconstruction", "share_round1", "copy_train_inputs"]

_log = logging.getLogger(__name__)

#: `AlignSettings.max_focal_log_std` that never refuses (finite so that it stays plain JSON).
FOCAL_PRIOR_OK = 1e9

#: Methods: baselines (a)-(e), the Table 2 ablations and the Table 3 round counts.
EVAL_METHODS = (
    "3dgs_gt_poses",        # (a) 3DGS on the noisy images with ground-truth poses
    "instantsplat",         # (b) our alignment + splat on the noisy images
    "nlm_instantsplat",     # (c) non-local means, then (b)
    "n2v_round1",           # (d) Denoise-GS round 1 only (= Table 2 "without the second round")
    "denoise_gs",           # (e) Denoise-GS, 2 rounds
    "ablate_no_selection",  # Table 2: round 2 on every view
    "ablate_charbonnier",   # Table 2: joint loss replaced by Charbonnier alone
    "rounds_1", "rounds_2", "rounds_3", "rounds_4",  # Table 3
    "n2v_fused_round1",     # extension: (d) with fuse_noisy_splat (see PipelineConfig)
    "denoise_gs_fused",     # extension: (e) with fuse_noisy_splat
    "oracle_clean",         # reference, not a competitor: (b) on the *clean* training photos
)
#: Methods of one round (the only ones `EvalConfig.denoiser` other than "n2v" can run).
ONE_ROUND_METHODS = ("3dgs_gt_poses", "instantsplat", "nlm_instantsplat", "oracle_clean", "n2v_round1",
                     "n2v_fused_round1")


@dataclass(frozen=True)
class EvalConfig:
    """Settings of `evaluate_dataset`.

    Attributes:
        methods: names from `EVAL_METHODS`.
        seeds: number of seeds (0 .. seeds-1).
        preset: pipeline preset for every method.
        views: K for rounds >= 2; None = min(12, number of training views).
        pose_fit_iters: held-out pose refinement steps; None = `splat`'s default.
        splat_iters: splat training iterations for every method; None = the preset's.
        device: torch device.
        allow_focal_prior: let alignment keep an undetermined focal length (the prior or its
            estimate) instead of refusing (`AlignSettings.max_focal_log_std`), as InstantSplat does;
            the held-out scores and pose errors then show the cost.
        denoiser: round 1's objective for the N2V-family methods (`DenoiseSettings.method`); other
            than "n2v" only the one-round methods may run, in folders named after it (`n2v_r2r`, ...).
    """

    methods: tuple[str, ...] = ("instantsplat", "nlm_instantsplat", "n2v_round1", "denoise_gs")
    seeds: int = 3
    preset: str = "default"
    views: int | None = None
    pose_fit_iters: int | None = None
    splat_iters: int | None = None
    device: str = "cpu"
    allow_focal_prior: bool = True
    denoiser: DenoiseMethod = "n2v"

    def __post_init__(self) -> None:
        unknown = [m for m in self.methods if m not in EVAL_METHODS]
        if unknown:
            raise InputError(f"unknown method(s) {unknown}", fix=f"choose from {', '.join(EVAL_METHODS)}")
        if self.denoiser not in DENOISE_METHODS:
            raise InputError(f"unknown denoiser {self.denoiser!r}", fix=f"choose from {', '.join(DENOISE_METHODS)}")
        multi_round = [m for m in self.methods if m not in ONE_ROUND_METHODS]
        if self.denoiser != "n2v" and multi_round:
            raise InputError(f"--denoiser {self.denoiser} runs round 1 only; these methods have more rounds: "
                             f"{', '.join(multi_round)}", fix=f"use {', '.join(ONE_ROUND_METHODS)}")
        if self.seeds < 1:
            raise InputError(f"--seeds must be at least 1, got {self.seeds}")
        preset(self.preset)


def row_label(method: str, config: EvalConfig) -> str:
    """The method's name in the results: with the denoiser appended when it is not N2V (`n2v_round1+r2r`)."""
    if config.denoiser == "n2v" or method not in ("n2v_round1", "n2v_fused_round1"):
        return method
    return f"{method}+{config.denoiser}"


def method_pipeline_config(method: str, base: PipelineConfig) -> tuple[str, PipelineConfig]:
    """(pipeline folder family, config) of a pipeline-based method; round count = config.rounds.

    Methods of one family differ only in the number of rounds, so they share a folder and its stages.
    Only the `*_fused` methods fuse (`PipelineConfig.fuse_noisy_splat`) and hand round 1's geometry to a
    round 2 whose own alignment pins the views less well (`AlignSettings.reuse_geometry`); every other
    method runs without either, whatever the preset says, so that (d), (e), the ablations and the
    baselines stay the paper's.
    """
    fused = method in ("n2v_fused_round1", "denoise_gs_fused")
    base = dataclasses.replace(base, fuse_noisy_splat=fused,
                               align=dataclasses.replace(base.align, reuse_geometry="auto" if fused else "never"))
    if method.startswith("rounds_"):
        return "n2v", dataclasses.replace(base, rounds=int(method.split("_")[1]))
    if method in ("n2v_round1", "denoise_gs"):
        return "n2v", dataclasses.replace(base, rounds=1 if method == "n2v_round1" else 2)
    if fused:
        return "n2v_fused", dataclasses.replace(base, rounds=1 if method == "n2v_fused_round1" else 2)
    if method in ("instantsplat", "nlm_instantsplat", "oracle_clean"):
        return method, dataclasses.replace(base, rounds=1)
    if method == "ablate_no_selection":
        return method, dataclasses.replace(base, rounds=2, select_views=False)
    if method == "ablate_charbonnier":
        return method, dataclasses.replace(base, rounds=2,
                                           denoise=dataclasses.replace(base.denoise, round2_loss="charbonnier"))
    raise ValueError(f"{method} is not a pipeline method")


# ----------------------------------------------------------------- classical "denoise" stages
def _identity_stage(ctx: StageContext) -> Mapping[str, object]:
    """(b): no denoising; the noisy images go to alignment and splatting as they are."""
    write_views(ctx.work_dir / "denoised", read_views(ctx.inputs["noisy"]))
    (ctx.work_dir / "n2v_model.pt").write_bytes(b"")  # no network in this method
    return {"denoiser": "none"}


def _nlm_stage(ctx: StageContext) -> Mapping[str, object]:
    """(c): scikit-image non-local means, h = 0.8 sigma (its documented recipe), sigma estimated per image."""
    from skimage.restoration import denoise_nl_means

    out, sigmas = {}, {}
    for name, img in read_views(ctx.inputs["noisy"]).items():
        sigma = estimate_noise_sigma(img)
        out[name] = denoise_nl_means(img, h=0.8 * sigma, sigma=sigma, fast_mode=True, patch_size=5,
                                     patch_distance=6, channel_axis=-1).astype(np.float32)
        sigmas[name] = sigma
    write_views(ctx.work_dir / "denoised", out)
    (ctx.work_dir / "n2v_model.pt").write_bytes(b"")
    return {"denoiser": "skimage.denoise_nl_means", "sigma_est": sigmas}


def _oracle_clean_stage(clean_files: Mapping[str, Path], ctx: StageContext) -> Mapping[str, object]:
    """`oracle_clean`: a perfect denoiser. The clean training photos go to alignment and splatting.

    It reads `clean/` of the training views, so it is not a method a user could run: it is the
    ceiling of every denoise-then-reconstruct method on the scene with these settings (what the
    alignment and the splat lose on noise-free photos), against which the denoisers' gains are read.
    """
    noisy = read_views(ctx.inputs["noisy"])
    missing = [n for n in noisy if n not in clean_files]
    if missing:
        raise InputError(f"oracle_clean: no clean image for {missing}", fix="use a dataset with clean/ for every view")
    write_views(ctx.work_dir / "denoised", {n: read_image(clean_files[n]) for n in noisy})
    (ctx.work_dir / "n2v_model.pt").write_bytes(b"")
    return {"denoiser": "oracle (clean photos)"}


# ----------------------------------------------------------------- helpers
def share_round1(src_run: Path, dst_run: Path) -> bool:
    """Seed `dst_run/round1` with hard links to a completed `src_run/round1` (same round-1 settings).

    The Table 2 ablations differ from `denoise_gs` only from round 2 on; linking round 1 lets
    their stage keys match it and skip it (the stage runner still checks every key, so a
    mismatch just re-runs). Returns True when something was linked.
    """
    src, dst = Path(src_run) / "round1", Path(dst_run) / "round1"
    if dst.exists() or not (src / "stages").is_dir():
        return False
    tmp = dst.with_name(".round1.link-tmp")
    shutil.rmtree(tmp, ignore_errors=True)

    def link(a: str, b: str) -> None:
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    shutil.copytree(src, tmp, copy_function=link,
                    ignore=lambda d, names: [n for n in names if n.startswith(".")])
    os.replace(tmp, dst)
    return True


def _stem_poses(model: SparseModel) -> dict[str, np.ndarray]:
    return {Path(n).stem: model.image(n).cam_from_world for n in model.names}


def copy_train_inputs(dataset: DatasetFolder, folder: Path, names: Sequence[str] | None = None) -> Path:
    """`folder` holding (hard links to) the dataset's noisy training images `names` (default: all of
    `dataset.train`), rebuilt atomically when it holds a different set; where `evaluate_dataset` runs."""
    names = list(dataset.train if names is None else names)
    if folder.is_dir() and sorted(p.stem for p in folder.iterdir()) == sorted(names):
        return folder
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name in names:
        src = dataset.images[name]
        try:
            os.link(src, tmp / src.name)
        except OSError:
            shutil.copy2(src, tmp / src.name)
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(tmp, folder)
    return folder


def heldout_camera(est_cameras: Sequence[Camera], gt_camera: Camera) -> Camera:
    """The reconstruction's own intrinsics for a held-out view of `gt_camera`'s size.

    A pose-free reconstruction is self-consistent with the intrinsics it estimated, not with the
    true ones (a focal error is absorbed into depths and poses), so its held-out views are rendered
    with its own camera, as InstantSplat evaluates: the median pinhole parameters of the
    estimated training cameras, rescaled to the held-out image size.
    """
    pars = []
    for c in est_cameras:
        fx, fy, cx, cy = _pinhole(c)
        sx, sy = gt_camera.width / c.width, gt_camera.height / c.height
        pars.append([fx * sx, fy * sy, cx * sx, cy * sy])
    return Camera("PINHOLE", gt_camera.width, gt_camera.height, np.median(np.asarray(pars), axis=0))


def _pinhole(c: Camera) -> tuple[float, float, float, float]:
    p = np.asarray(c.params, np.float64)
    if c.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        return p[0], p[0], p[1], p[2]
    return p[0], p[1], p[2], p[3]


def _score_scene(model, gt: SparseModel, est_train: Mapping[str, np.ndarray] | None, dataset: DatasetFolder,
                 config: EvalConfig, est_cameras: Sequence[Camera] = (),
                 renders_out: dict[str, np.ndarray] | None = None
                 ) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """Held-out renders scored against clean images; training-pose errors (None = GT poses used).

    `renders_out`, when given, receives the held-out renders (stem -> (H, W, 3) float image).
    """
    render_views = require("splat.render", "render_views", needed_for="denoise-gs eval")
    fit_pose = require("splat.pose_fit", "fit_pose", needed_for="denoise-gs eval")
    gt_poses = _stem_poses(gt)
    ref_train = {n: gt_poses[n] for n in dataset.train}
    ref_test = {n: gt_poses[n] for n in dataset.test}
    cams = {Path(n).stem: gt.camera_of(n) for n in gt.names}
    if est_train is not None and est_cameras:
        cams = {n: heldout_camera(est_cameras, c) for n, c in cams.items()}
    pose_stats = {"rot_err_deg": float("nan"), "ate": float("nan")}
    if est_train is None:
        test_poses = ref_test
    else:
        test_poses = map_cameras_local(est_train, ref_train, ref_test).cam_from_world
        compare_poses = require("mvgeo.metrics", "compare_poses", needed_for="denoise-gs eval")
        pm = compare_poses(est_train, ref_train)
        pose_stats = {"rot_err_deg": float(pm.median_rotation_deg),
                      "ate": float(pm.ate.rmse) if pm.ate is not None else float("nan")}
    renders, targets, names = [], [], []
    for n in dataset.test:
        pose = test_poses[n]
        if est_train is not None:
            noisy = read_image(dataset.images[n])
            pose = fit_pose(model, noisy, cams[n], pose, iters=config.pose_fit_iters)
        renders.append(render_views(model, [cams[n]], np.asarray(pose)[None, :3])[0])
        targets.append(read_image(dataset.clean[n]))
        names.append(n)
    scores = score_images(renders, targets)
    if renders_out is not None:
        renders_out.update(zip(names, renders, strict=True))
    per_view = {n: {"psnr_db": float(scores.psnr_db[i]), "ssim": float(scores.ssim[i]),
                    "lpips": float(scores.lpips[i])} for i, n in enumerate(names)}
    return per_view, pose_stats


def score_reconstruction(run_dir: Path, dataset: DatasetFolder, train_names: list[str] | None = None, *,
                         pose_fit_iters: int | None = None, device: str = "cpu") -> dict[str, float]:
    """Score a finished pipeline round folder (`point_cloud.ply`, `sparse/0/`) as `evaluate_dataset` does.

    Args:
        run_dir: e.g. `OUT/round2`.
        dataset: the dataset it was built from.
        train_names: the training views it saw (default `dataset.train`).

    Returns:
        Held-out means ``psnr_db``, ``ssim``, ``lpips`` and pose errors ``rot_err_deg``, ``ate``.
    """
    read_ply = require("splat.ply", "read_gaussian_ply", needed_for="scoring")
    gt = read_sparse_model(dataset.root / "sparse" / "0")
    model = read_ply(Path(run_dir) / "point_cloud.ply", device=device)
    est_model = read_sparse_model(Path(run_dir) / "sparse" / "0")
    est = _stem_poses(est_model)
    ds = dataclasses.replace(dataset, train=list(train_names or dataset.train))
    per_view, pose_stats = _score_scene(model, gt, est, ds, EvalConfig(pose_fit_iters=pose_fit_iters),
                                        [est_model.camera_of(n) for n in est_model.names])
    means = {m: float(np.mean([v[m] for v in per_view.values()])) for m in ("psnr_db", "ssim", "lpips")}
    return {**means, **pose_stats}


def _run_gt_poses(dataset: DatasetFolder, gt: SparseModel, base: PipelineConfig, seed: int, device: str):
    """(a): splat training on the noisy training images with ground-truth poses (no pose learning)."""
    need = "3dgs_gt_poses"
    train_gaussians = require("splat.train", "train_gaussians", needed_for=need)
    presets = require("splat.train", "TRAIN_PRESETS", needed_for=need)
    cfg = dataclasses.replace(presets["gt_poses"], seed=seed,
                              **({"iters": base.splat.iters} if base.splat.iters else {}))
    by_stem = {Path(n).stem: n for n in gt.names}
    names = [by_stem[s] for s in dataset.train]
    images = [read_image(dataset.images[s]) for s in dataset.train]
    cams = [gt.camera_of(n) for n in names]
    cfw = np.stack([gt.image(n).cam_from_world for n in names])
    if (dataset.root / "depth").is_dir():
        load_views = require("splat.dataset", "load_views", needed_for=need)
        points_from_depth = require("splat.dataset", "points_from_depth", needed_for=need)
        views = load_views(dataset.root, split="train")
        xyz, rgb = points_from_depth(dataset.root, views)
    elif len(gt.points_xyz):
        xyz, rgb = gt.points_xyz, gt.points_rgb
    else:
        raise InputError("3dgs_gt_poses needs initial points: no depth/ maps and no points in sparse/0",
                         path=dataset.root, fix="use a data_synth dataset (it ships depth/) or a model with points")
    return train_gaussians(images, cams, cfw, xyz, rgb, cfg, device=device).model


def _run_method(method: str, seed: int, dataset: DatasetFolder, gt: SparseModel, base: PipelineConfig,
                inputs: Path, out: Path, config: EvalConfig, *, scene: str) -> RunScores:
    """Run (or reuse) one method with one seed and score it."""
    start = time.perf_counter()
    if method == "3dgs_gt_poses":
        model = _run_gt_poses(dataset, gt, dataclasses.replace(base, seed=seed), seed, config.device)
        est, est_cams = None, []
        seconds = time.perf_counter() - start
    else:
        family, cfg = method_pipeline_config(method, dataclasses.replace(base, seed=seed))
        if family in ("n2v", "n2v_fused") and config.denoiser != "n2v":
            family = f"{family}_{config.denoiser}"
            cfg = dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, method=config.denoiser))
        stages = dataclasses.replace(product_stages(), export=None)  # the scores need no viewer files
        if method == "instantsplat":
            stages = dataclasses.replace(stages, denoise=_identity_stage)
        elif method == "nlm_instantsplat":
            stages = dataclasses.replace(stages, denoise=_nlm_stage)
        elif method == "oracle_clean":
            stages = dataclasses.replace(stages, denoise=functools.partial(_oracle_clean_stage, dataset.clean))
        seed_dir = out / "runs" / scene / f"seed{seed}"
        if method.startswith("ablate_"):
            share_round1(seed_dir / "n2v", seed_dir / family)
        res = run_pipeline(inputs, seed_dir / family, cfg, stages=stages)
        final = res.rounds[-1].dir
        read_ply = require("splat.ply", "read_gaussian_ply", needed_for="denoise-gs eval")
        model = read_ply(final / "point_cloud.ply", device=config.device)
        est_model = read_sparse_model(final / "sparse" / "0")
        est = _stem_poses(est_model)
        est_cams = [est_model.camera_of(n) for n in est_model.names]
        # The stages' own recorded wall time (a stage reused from the cache, e.g. round 1 shared by
        # n2v_round1 / denoise_gs / rounds_N, reports the time it took when it ran).
        seconds = float(sum(st.seconds for rd in res.rounds for st in rd.stages.values()))
    held_out: dict[str, np.ndarray] = {}
    per_view, pose_stats = _score_scene(model, gt, est, dataset, config, est_cams, renders_out=held_out)
    save_heldout_renders(out / "heldout" / scene, method, seed, held_out, dataset)
    means = {m: float(np.mean([v[m] for v in per_view.values()])) for m in ("psnr_db", "ssim", "lpips")}
    return RunScores(scene, row_label(method, config), seed, **means, **pose_stats, seconds=seconds, per_view=per_view)


def save_heldout_renders(folder: Path, method: str, seed: int, renders: Mapping[str, np.ndarray],
                         dataset: DatasetFolder) -> None:
    """Keep a run's held-out renders for the figures: `folder/<method>/seed<k>/<view>.png`, and once
    per scene the clean and noisy held-out images (`folder/_clean/`, `folder/_noisy/`)."""
    write_views(folder / method / f"seed{seed}", dict(renders))
    for part, files in (("_clean", dataset.clean), ("_noisy", dataset.images)):
        if not (folder / part).is_dir():
            write_views(folder / part, {n: read_image(files[n]) for n in dataset.test if n in files})


def evaluate_dataset(dataset: DatasetFolder, out: Path, config: EvalConfig, *, scene: str,
                     on_row: Callable[[list[RunScores]], None] | None = None) -> list[RunScores]:
    """Run and score every method x seed on one dataset; returns one `RunScores` per run.

    `on_row(rows_so_far)` is called after each run (the CLI rewrites results.md, so an interrupted
    evaluation keeps what it measured).

    Raises:
        InputError: dataset problems (found before any compute).
        MissingComponentError: a component a method needs is not available (checked up front).
    """
    out = Path(out)
    gt = read_sparse_model(dataset.root / "sparse" / "0")
    missing = [n for n in dataset.train + dataset.test if n not in _stem_poses(gt)]
    if missing:
        raise InputError(f"views {missing} have no ground-truth camera", path=dataset.root / "sparse" / "0")
    k = config.views or min(12, len(dataset.train))
    # The dataset is at its working size already (`denoise-gs eval --max-size`, eval.pipeline.inputs):
    # the runs keep it, so renders and the clean images stay pixel-aligned.
    base = dataclasses.replace(preset(config.preset, views=k, device=config.device), max_size=None)
    if config.splat_iters is not None:
        base = dataclasses.replace(base, splat=dataclasses.replace(base.splat, iters=config.splat_iters))
    if config.allow_focal_prior:
        base = dataclasses.replace(base, align=dataclasses.replace(base.align, max_focal_log_std=FOCAL_PRIOR_OK))
    pipeline_methods = [m for m in config.methods if m != "3dgs_gt_poses"]
    for m in pipeline_methods:  # fail before any compute if a component is missing
        check_product_components(method_pipeline_config(m, base)[1])
    for name in ("render_views", "fit_pose"):
        require("splat.render" if name == "render_views" else "splat.pose_fit", name, needed_for="denoise-gs eval")
    inputs = copy_train_inputs(dataset, out / "inputs" / scene)
    rows: list[RunScores] = []
    for seed in range(config.seeds):
        for method in sorted(config.methods, key=EVAL_METHODS.index):  # ablations after the round 1 they share
            _log.info("eval %s: %s, seed %d", scene, method, seed)
            try:
                rows.append(_run_method(method, seed, dataset, gt, base, inputs, out, config, scene=scene))
            except (DgsError, RuntimeError, ValueError, ArithmeticError, OSError, cv2.error) as exc:
                # One method failing (e.g. alignment on a hard input) must not lose the others: the
                # row is kept with NaN metrics and the error, and the table shows it as failed.
                _log.error("eval %s: %s, seed %d failed: %s: %s", scene, method, seed, type(exc).__name__, exc)
                nan = float("nan")
                rows.append(RunScores(scene, row_label(method, config), seed, nan, nan, nan,
                                      error=f"{type(exc).__name__}: {exc}"))
            if on_row is not None:
                on_row(list(rows))
    return rows


def scene_dataset(kind: str, source: Path | str, out: Path, *, size_wh: tuple[int, int] | None = None,
                  views: int | None = None) -> tuple[str, Path]:
    """(scene name, dataset folder): dataset folders as they are, scenes rendered into `out/data/<name>`.

    Args:
        kind, source: from `eval.cli.resolve_scene_source`.
        out: the evaluation folder.
        size_wh, views: image size and view count overrides for rendered scenes (None: the scene's).
    """
    if kind == "dataset":
        return Path(source).name, Path(source)
    render_scene = require("data_synth", "render_scene", needed_for="denoise-gs eval on a scene")
    name = Path(source).stem if kind == "scene_file" else str(source)
    tag = "" if size_wh is None and views is None else f"_{size_wh[0]}x{size_wh[1]}" if size_wh else ""
    tag += f"_{views}v" if views is not None else ""
    folder = out / "data" / f"{name}{tag}"
    if not (folder / "split.json").is_file():
        render_scene(source, folder, size_wh=size_wh, views=views)
    return name, folder

