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
  clean images serve scoring only; two Adam fits, at the full and a quarter of the learning rate, the pose of
  lowest loss kept, since the full rate alone can overshoot and stay at the start), then rendered;
- held-out renders are scored against the clean images (PSNR, SSIM, LPIPS),
  training poses against ground truth (`mvgeo.metrics.compare_poses`).

The methods are listed in `eval.methods.METHODS`. Methods that share settings
share a pipeline folder, so `n2v_round1`, `denoise_gs` and `rounds_N` reuse each
other's completed rounds (the stage keys match). The dataset (noise realisation)
is the same for every seed; the seed drives the methods' own randomness.

Method (a) `3dgs_gt_poses` trains the pipeline's splat stage on the noisy
training images with the ground-truth poses, initialised from the ground-truth
depth maps (an oracle initialisation, so it is an optimistic baseline) or,
without depth maps, from the ground-truth model's points.

`oracle_clean` is a reference, not a competitor: (b)'s alignment and the preset's
splat (the product's length) on the *clean* training photos, i.e. a perfect
denoiser. It is the ceiling of every denoise-then-reconstruct method with the
same settings. The baselines and the paper's loop splat for InstantSplat's 1000
iterations under every preset (`eval.methods.paper_loop`).

Each (scene, method, seed) is one call, `run_task(EvalTask)`, whose argument is
plain picklable data. A method that cannot handle the input, by a documented
error (`FAILED_RUN_ERRORS`), gives a "failed" row; an error about the output
folder itself (files in a run folder the evaluation did not write, a run folder
that is not one) stops the evaluation; any other exception is a bug and
propagates.

The evaluation changes only files it wrote: the held-out renders
(`OUT/heldout/<scene>/`) are committed with records (`OUT/heldout/stages/`,
`save_heldout_renders`), the results with theirs (`eval.results`), and before
any run every file the evaluation may replace (results, held-out renders, the
run folders' stage outputs) is checked (`check_eval_outputs`).
"""

from __future__ import annotations

import dataclasses
import filecmp
import json
import logging
import os
import shutil
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from eval.distributed import chain_after
from eval.heldout import map_cameras_local
from eval.image_metrics import score_images
from eval.methods import METHODS, EvalMethod, reconstruct, with_splat_iters
from eval.pipeline import PipelineConfig, preset
from eval.pipeline.config import DENOISE_METHODS, DenoiseMethod
from eval.pipeline.hashing import source_digest
from eval.pipeline.run import RUN_COMMAND, SCENE_OUTPUTS, planned_run_outputs
from eval.pipeline.stage import (
    RECORD_DIR,
    OwnershipCheck,
    UnownedOutputError,
    adopt_outputs,
    check_outputs_owned,
    commit_written,
)
from eval.pipeline.stage_settings import check_settings, round_settings
from eval.pipeline.stages import MODEL_FILE
from eval.pipeline.validate import DatasetFolder
from eval.pipeline.views import write_views
from eval.results import RunScores, check_results_owned
from mvgeo.camera import Camera
from mvgeo.common.atomic import atomic_write_text
from mvgeo.common.errors import DegenerateGeometryError, InputError
from mvgeo.common.imageio import read_image
from mvgeo.common.output import prepare_output
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import SparseModel, read_sparse_model
from splat.ply import read_gaussian_ply
from splat.pose_fit import fit_pose
from splat.render import render_views

if TYPE_CHECKING:
    from eval.distributed import RayExecutor

__all__ = ["FAILED_RUN_ERRORS", "HELDOUT_DIR", "EvalConfig", "EvalTask", "base_pipeline_config",
           "check_eval_outputs", "copy_train_inputs", "evaluate_dataset", "heldout_record",
           "expected_costs", "run_task", "save_heldout_references", "save_heldout_renders", "scene_dataset",
           "score_reconstruction", "share_keys", "task_graph"]

_log = logging.getLogger(__name__)

#: `AlignSettings.max_focal_log_std` that never refuses (finite so that it stays plain JSON).
FOCAL_PRIOR_OK = 1e9

#: The documented errors by which a method says it cannot handle an input: bad or missing data
#: (`InputError`, e.g. `oracle_clean` without clean photos, `3dgs_gt_poses` without initial points) and
#: geometry without a unique answer (`DegenerateGeometryError`, e.g. alignment that cannot determine the
#: cameras). Such a run becomes a "failed" row, unless the error is about the output folder itself
#: (`run_task`); any other exception is a bug and surfaces.
FAILED_RUN_ERRORS: tuple[type[Exception], ...] = (InputError, DegenerateGeometryError)
#: The held-out renders' folder in OUT: `<scene>/<method>/seed<k>/`, `<scene>/_clean/`, `<scene>/_noisy/`,
#: and their records in `stages/`.
HELDOUT_DIR = "heldout"


def _about_run_folder(exc: Exception, seed_dir: Path) -> bool:
    """`exc` is about the output folder, not the method: files in a run folder that the evaluation did not
    write or that changed (`UnownedOutputError`), or a run folder refused as a whole (not a run's folder,
    another process writing it: an `InputError` naming a folder of `seed_dir`)."""
    if isinstance(exc, UnownedOutputError):
        return True
    path = getattr(exc, "path", None)
    return isinstance(exc, InputError) and path is not None and Path(path).parent == seed_dir


def base_pipeline_config(config: EvalConfig, views: int) -> PipelineConfig:
    """The pipeline configuration every method of an evaluation starts from: `config.preset` at the working
    size (`max_size=None`), with K = `views` and the evaluation's overrides."""
    base = dataclasses.replace(preset(config.preset, views=views, device=config.device), max_size=None)
    if config.allow_focal_prior:
        base = dataclasses.replace(base, align=dataclasses.replace(base.align, max_focal_log_std=FOCAL_PRIOR_OK))
    if config.grouped_wiener is not None:
        base = dataclasses.replace(base, denoise=dataclasses.replace(base.denoise,
                                                                     grouped_wiener=config.grouped_wiener))
    if config.grouped_wiener_passes is not None:
        base = dataclasses.replace(base, denoise=dataclasses.replace(
            base.denoise, grouped_wiener=True, grouped_wiener_passes=config.grouped_wiener_passes))
    if config.noisy_detail is not None:
        base = dataclasses.replace(base, splat=dataclasses.replace(base.splat, noisy_detail=config.noisy_detail))
    if config.pd_stride is not None:
        base = dataclasses.replace(base, denoise=dataclasses.replace(base.denoise, pd_stride=config.pd_stride))
    if config.noise_model is not None:
        base = dataclasses.replace(base, denoise=dataclasses.replace(base.denoise, noise_model=config.noise_model))
    if config.pass_clean_below is not None:
        base = dataclasses.replace(base, denoise=dataclasses.replace(base.denoise,
                                                                     pass_clean_below_255=config.pass_clean_below))
    return base


@dataclass(frozen=True)
class EvalConfig:
    """Settings of `evaluate_dataset`.

    Attributes:
        methods: names from `eval.methods.METHODS`.
        seeds: number of seeds: `first_seed` .. `first_seed + seeds - 1`.
        first_seed: the first seed (default 0). An evaluation in parts (`--first-seed 1 --seeds 2` after
            `--seeds 1`) runs each seed once; into the same folder, with the same code and settings, its
            table keeps the earlier seeds' rows (`eval.results.carried_rows`).
        preset: pipeline preset for every method.
        views: K for rounds >= 2; None = min(12, number of training views).
        pose_fit_iters: held-out pose refinement steps; None = `splat`'s default.
        splat_iters: splat training iterations for every method, the baselines' included; None = each
            method's own: the preset's for the product and the clean-photo oracle, InstantSplat's 1000
            for the baselines and the paper's loop (`eval.methods.paper_loop`).
        device: torch device.
        allow_focal_prior: let alignment keep an undetermined focal length (the prior or its
            estimate) instead of refusing (`AlignSettings.max_focal_log_std`), as InstantSplat does;
            the held-out scores and pose errors then show the cost.
        denoiser: round 1's objective for the N2V-family methods (`DenoiseSettings.method`); other
            than "n2v" only methods of one round may run, in folders named after it (`n2v_r2r`, ...).
        grouped_wiener: the grouped Wiener step on or off for every method that trains the UNet
            (`DenoiseSettings.grouped_wiener`); None: the preset's. For A/B measurements: evaluate each
            setting into its own output folder.
        grouped_wiener_passes: passes of the grouped Wiener step (`DenoiseSettings.grouped_wiener_passes`;
            it turns the step on); None: the preset's. For A/B measurements, as `grouped_wiener`.
        noisy_detail: the noisy photos' band in the splat's target (`SplatSettings.noisy_detail`) for the
            methods that take the preset's (`product`; the paper's loop, the baselines and the oracle train
            on their photos as they are); None: the preset's. For A/B measurements, as `grouped_wiener`.
        pd_stride: round 1's pixel-shuffle stride for every method that trains the UNet
            (`DenoiseSettings.pd_stride`); None: the preset's. For A/B measurements, as `grouped_wiener`.
        noise_model: the denoisers' noise model for every method that trains the UNet
            (`DenoiseSettings.noise_model`); None: measured from the photos.
        pass_clean_below: round 1's pass-through level (/255) for the methods that take the preset's
            (`DenoiseSettings.pass_clean_below_255`; the paper's loop always denoises); None: the preset's.
    """

    methods: tuple[str, ...] = ("instantsplat", "nlm_instantsplat", "n2v_round1", "denoise_gs")
    seeds: int = 3
    first_seed: int = 0
    preset: str = "default"
    views: int | None = None
    pose_fit_iters: int | None = None
    splat_iters: int | None = None
    device: str = "cpu"
    allow_focal_prior: bool = True
    denoiser: DenoiseMethod = "n2v"
    grouped_wiener: bool | None = None
    grouped_wiener_passes: int | None = None
    noisy_detail: float | None = None
    pd_stride: int | None = None
    noise_model: str | None = None
    pass_clean_below: float | None = None

    def __post_init__(self) -> None:
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown:
            raise InputError(f"unknown method(s) {unknown}", fix=f"choose from {', '.join(METHODS)}")
        if self.denoiser not in DENOISE_METHODS:
            raise InputError(f"unknown denoiser {self.denoiser!r}", fix=f"choose from {', '.join(DENOISE_METHODS)}")
        multi_round = [m for m in self.methods if (METHODS[m].rounds or 1) > 1]
        if self.denoiser != "n2v" and multi_round:
            one_round = [m.name for m in METHODS.values() if m.rounds == 1]
            raise InputError(f"--denoiser {self.denoiser} runs round 1 only; these methods have more rounds: "
                             f"{', '.join(multi_round)}", fix=f"use {', '.join(one_round)}")
        if self.seeds < 1:
            raise InputError(f"--seeds must be at least 1, got {self.seeds}")
        if self.first_seed < 0:
            raise InputError(f"--first-seed must be at least 0, got {self.first_seed}")
        if self.grouped_wiener_passes is not None and (self.grouped_wiener is False or self.grouped_wiener_passes < 1):
            raise InputError(f"--grouped-wiener-passes {self.grouped_wiener_passes} needs the step on and at least "
                             "one pass", fix="give one of --no-grouped-wiener and --grouped-wiener-passes N >= 1")
        if self.noisy_detail is not None and not 0.0 <= self.noisy_detail <= 1.0:
            raise InputError(f"--noisy-detail must be in [0, 1], got {self.noisy_detail}")
        preset(self.preset)

    @property
    def seed_values(self) -> range:
        """The seeds every method runs with, in order."""
        return range(self.first_seed, self.first_seed + self.seeds)

    def selected(self) -> list[EvalMethod]:
        """The chosen methods in the registry's order (the ablations after the round 1 they share)."""
        chosen = [m for m in METHODS.values() if m.name in self.methods]
        return chosen if self.splat_iters is None else [with_splat_iters(m, self.splat_iters) for m in chosen]


# ----------------------------------------------------------------- helpers
def _stem_poses(model: SparseModel) -> dict[str, np.ndarray]:
    return {Path(n).stem: model.image(n).cam_from_world for n in model.names}


def _same_image(path: Path, src: Path) -> bool:
    """`path` is a plain file with `src`'s bytes (a hard link to it, or a copy)."""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        return os.path.samefile(path, src) or filecmp.cmp(path, src, shallow=False)
    except OSError:
        return False


def copy_train_inputs(dataset: DatasetFolder, folder: Path, names: Sequence[str] | None = None) -> Path:
    """`folder` holding (hard links to) the dataset's noisy training images `names` (default: all of
    `dataset.train`), rebuilt atomically when it holds a different set or other bytes; where
    `evaluate_dataset` runs.

    Only what this function put there is ever replaced: the links it makes are recorded
    (`stages/inputs.<folder name>.json` beside `folder`, as a stage records its outputs), and a folder holding
    anything else, or a recorded file that changed, is refused. A folder without a record (written before
    records existed) is taken as its own while it holds only the dataset's images (by name and bytes).

    Raises:
        InputError: `folder` is not a folder, or holds something this function did not put there
            (`UnownedOutputError`; nothing is changed).
    """
    names = list(dataset.train if names is None else names)
    wanted = {dataset.images[n].name: dataset.images[n] for n in names}
    stage_dir, record = folder.parent, f"inputs.{folder.name}"
    if os.path.lexists(folder):
        if folder.is_symlink() or not folder.is_dir():
            raise InputError("the training-image folder of the evaluation is not a folder", path=folder,
                             fix="move it out of the evaluation folder, or choose another --out")
        entries = sorted(folder.iterdir())
        if (stage_dir / RECORD_DIR / f"{record}.json").is_file():
            check_outputs_owned(stage_dir, record, (folder.name,))
        else:
            by_name = {p.name: p for p in dataset.images.values()}
            foreign = [e for e in entries if e.name not in by_name or not _same_image(e, by_name[e.name])]
            if foreign:
                raise UnownedOutputError(record, stage_dir, [f"{e} (not one of the dataset's images)"
                                                             for e in foreign])
            adopt_outputs(stage_dir, record, (folder.name,))  # the dataset's own images: this function's
        if (sorted(e.name for e in entries) == sorted(wanted)
                and all(_same_image(folder / n, src) for n, src in wanted.items())):
            return folder

    def link(work: Path) -> None:
        (work / folder.name).mkdir()
        for src in wanted.values():
            try:
                os.link(src, work / folder.name / src.name)
            except OSError:
                shutil.copy2(src, work / folder.name / src.name)

    commit_written(stage_dir, record, (folder.name,), link)
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
        Held-out means ``psnr_db``, ``ssim``, ``lpips`` and the training poses' errors ``rot_err_deg`` (the median
        relative rotation error over pairs of views) and ``ate``.
    """
    gt = read_sparse_model(dataset.root / "sparse" / "0")
    model = read_gaussian_ply(Path(run_dir) / "point_cloud.ply", device=device)
    est_model = read_sparse_model(Path(run_dir) / "sparse" / "0")
    est = _stem_poses(est_model)
    ds = dataclasses.replace(dataset, train=list(train_names or dataset.train))
    per_view, pose_stats = _score_scene(model, gt, est, ds, EvalConfig(pose_fit_iters=pose_fit_iters),
                                        [est_model.camera_of(n) for n in est_model.names])
    means = {m: float(np.mean([v[m] for v in per_view.values()])) for m in ("psnr_db", "ssim", "lpips")}
    return {**means, **pose_stats}


@dataclass(frozen=True)
class EvalTask:
    """One method with one seed on one scene: the argument of `run_task`, plain picklable data.

    Attributes:
        scene: the scene's name in the results.
        method: the method (`eval.methods.METHODS`).
        seed: the methods' seed.
        dataset: the checked dataset (held-out views, clean images, ground-truth cameras).
        base: the pipeline settings every method starts from (`EvalMethod.configure`).
        inputs: the folder of noisy training images the method sees (`copy_train_inputs`).
        out: the evaluation folder (`runs/`, `heldout/` are written under it).
        config: the evaluation's settings (device, held-out pose fitting, denoiser).
    """

    scene: str
    method: EvalMethod
    seed: int
    dataset: DatasetFolder
    base: PipelineConfig
    inputs: Path
    out: Path
    config: EvalConfig


def run_task(task: EvalTask) -> RunScores:
    """Run (or resume) one method with one seed and score it on the held-out views.

    Returns:
        The run's scores; a "failed" row (NaN metrics, the error) when the method raised one of
        `FAILED_RUN_ERRORS`.

    Raises:
        UnownedOutputError: the run folder, or the held-out renders' folder,
            holds files the evaluation did not write or that changed since; nothing of them was changed.
        InputError: a run folder is refused as a whole (not a `denoise-gs run` folder, another process
            writing it).
        Any other exception of the method or the scoring (a bug, not a property of the input).
    """
    method, config = task.method, task.config
    label = method.row_label(config.denoiser)
    seed_dir = task.out / "runs" / task.scene / f"seed{task.seed}"
    try:
        rec = reconstruct(method, task.dataset, task.base, seed=task.seed, denoiser=config.denoiser,
                          inputs=task.inputs, seed_dir=seed_dir)
        gt = read_sparse_model(task.dataset.root / "sparse" / "0")
        model = read_gaussian_ply(rec.round_dir / "point_cloud.ply", device=config.device)
        est, est_cams = None, []
        if rec.estimated_poses:
            est_model = read_sparse_model(rec.round_dir / "sparse" / "0")
            est = _stem_poses(est_model)
            est_cams = [est_model.camera_of(n) for n in est_model.names]
        held_out: dict[str, np.ndarray] = {}
        per_view, pose_stats = _score_scene(model, gt, est, task.dataset, config, est_cams, renders_out=held_out)
    except FAILED_RUN_ERRORS as exc:
        if _about_run_folder(exc, seed_dir):  # the output folder, not the method: the evaluation stops
            raise
        # One method failing on a hard input (e.g. alignment that cannot determine the cameras) must not
        # lose the others: the row is kept with NaN metrics and the error, and the table shows it as failed.
        _log.error("eval %s: %s, seed %d failed: %s: %s", task.scene, method.name, task.seed,
                   type(exc).__name__, exc)
        nan = float("nan")
        return RunScores(task.scene, label, task.seed, nan, nan, nan, error=f"{type(exc).__name__}: {exc}")
    save_heldout_renders(task.out / HELDOUT_DIR / task.scene, method.name, task.seed, held_out, task.dataset)
    means = {m: float(np.mean([v[m] for v in per_view.values()])) for m in ("psnr_db", "ssim", "lpips")}
    return RunScores(task.scene, label, task.seed, **means, **pose_stats, seconds=rec.seconds, per_view=per_view)


def heldout_record(scene: str, method: str | None, seed: int = 0) -> str:
    """The record name (in `OUT/heldout/stages/`) of a run's held-out renders, or with `method` None of the
    scene's clean and noisy held-out images."""
    return f"{scene}.references" if method is None else f"{scene}.{method}.seed{seed}"


def _heldout_outputs(scene: str, method: str | None, seed: int = 0) -> tuple[str, ...]:
    """What `heldout_record(scene, method, seed)` records, relative to `OUT/heldout`."""
    return (f"{scene}/_clean", f"{scene}/_noisy") if method is None else (f"{scene}/{method}/seed{seed}",)


def save_heldout_renders(folder: Path, method: str, seed: int, renders: Mapping[str, np.ndarray],
                         dataset: DatasetFolder) -> None:
    """Keep a run's held-out renders for the figures: `folder/<method>/seed<k>/<view>.png` (`folder` is
    `OUT/heldout/<scene>`), and the clean and noisy held-out images (`save_heldout_references`) when
    `folder/_clean/` is not there yet. Each is committed with its record (`heldout_record`) in
    `folder/../stages/`, replacing only what an earlier call wrote.

    Raises:
        UnownedOutputError: `folder/<method>/seed<k>/` holds files this function did not write there or that
            changed since (nothing is replaced).
    """
    folder = Path(folder)
    scene = folder.name
    commit_written(folder.parent, heldout_record(scene, method, seed), _heldout_outputs(scene, method, seed),
                   lambda work: write_views(work / scene / method / f"seed{seed}", dict(renders)))
    if not (folder / "_clean").is_dir():
        save_heldout_references(folder, dataset)


def save_heldout_references(folder: Path, dataset: DatasetFolder) -> None:
    """Write the clean and noisy held-out images of `dataset` into `folder/_clean/` and `folder/_noisy/`
    (`folder` is `OUT/heldout/<scene>`), committed with their record (`heldout_record(scene, None)`).

    Raises:
        UnownedOutputError: those folders hold files this function did not write or that changed.
    """
    folder = Path(folder)
    scene = folder.name

    def write(work: Path) -> None:
        for part, files in (("_clean", dataset.clean), ("_noisy", dataset.images)):
            write_views(work / scene / part, {n: read_image(files[n]) for n in dataset.test if n in files})

    commit_written(folder.parent, heldout_record(scene, None), _heldout_outputs(scene, None), write)


def _run_stage_outputs(method: EvalMethod, dataset: DatasetFolder, base: PipelineConfig, seed: int,
                       denoiser: DenoiseMethod, seed_dir: Path
                       ) -> Iterator[tuple[Path | None, Path, str, tuple[str, ...]]]:
    """(run folder, stage folder, stage name, outputs) of every stage `eval.methods.reconstruct` may run for
    `method` (the runs it makes first included); the run folder is that of a `run_pipeline` run, None for
    the ground-truth-pose splat (it opens no run folder)."""
    config = method.pipeline_config(dataclasses.replace(base, seed=seed), denoiser)
    folder = seed_dir / method.folder(denoiser)
    if method.gt_pose_variant_of is not None:
        yield from _run_stage_outputs(method.gt_pose_variant_of, dataset, base, seed, denoiser, seed_dir)
        if method.gt_pose_points_from not in (None, method.gt_pose_variant_of):
            yield from _run_stage_outputs(method.gt_pose_points_from, dataset, base, seed, denoiser, seed_dir)
    if method.ground_truth_poses:
        for name in ("align", "splat"):
            yield None, folder / "round1", name, SCENE_OUTPUTS[name]
        return
    settings = [round_settings(config, r) for r in range(1, config.rounds + 1)]
    for stage_dir, name, outputs in planned_run_outputs(folder, method.stages(dataset), settings):
        yield folder, stage_dir, name, outputs


def check_eval_outputs(tasks: Sequence[EvalTask]) -> None:
    """Check, before any run, that the evaluation of `tasks` (one output folder and scene) would replace or
    delete only files it wrote: its results (`eval.results.check_results_owned`), the held-out renders of
    every task and the scene's clean and noisy held-out images, and every stage output of the runs
    (`eval.methods.reconstruct`'s, as `run_pipeline` checks them); and that each run folder can be opened
    (`prepare_output`). One error names every file found.

    Raises:
        UnownedOutputError: files the evaluation did not write, or that changed since, where it writes.
        InputError: a run folder is refused as a whole (e.g. a folder of the user's at its path).
    """
    if not tasks:
        return
    out, scene = tasks[0].out, tasks[0].scene
    owned = OwnershipCheck()
    check = owned.check
    check(check_results_owned, out)
    heldout = out / HELDOUT_DIR
    check(check_outputs_owned, heldout, heldout_record(scene, None), _heldout_outputs(scene, None))
    run_folders: dict[Path, None] = {}
    stage_outputs: dict[tuple[Path, str, tuple[str, ...]], None] = {}
    for t in tasks:
        check(check_outputs_owned, heldout, heldout_record(scene, t.method.name, t.seed),
              _heldout_outputs(scene, t.method.name, t.seed))
        seed_dir = out / "runs" / scene / f"seed{t.seed}"
        for folder, stage_dir, name, outputs in _run_stage_outputs(t.method, t.dataset, t.base, t.seed,
                                                                   t.config.denoiser, seed_dir):
            if folder is not None:
                run_folders[folder] = None
            stage_outputs[stage_dir, name, outputs] = None
    for folder in run_folders:
        prepare_output(folder, command=RUN_COMMAND, resume=True)
    for stage_dir, name, outputs in stage_outputs:
        check(check_outputs_owned, stage_dir, name, outputs, defer_hidden=True)
    owned.raise_if_any(out)


def share_keys(task: EvalTask) -> tuple[tuple[str, int, str], ...]:
    """The pipeline folders a task writes or reads as (scene, seed, folder) keys. The ablations key on the
    folder whose round 1 they link (`EvalMethod.shares_round1_with`), a `@gt_poses` variant on its method's
    folder and its points' method's (`EvalMethod.runs_after`)."""
    return tuple((task.scene, task.seed, f) for f in task.method.runs_after(task.config.denoiser))


def task_graph(tasks: Sequence[EvalTask]) -> list[tuple[int, ...]]:
    """For each task (in the serial order), the earlier tasks it waits for (`eval.distributed.chain_after`).

    A task writes the folders of `share_keys`, and runs after the last earlier task with any of them;
    but a `@gt_poses` variant only reads its method's and its points' method's folders where an earlier
    task of the same scene and seed has run that method (each folder judged on its own): it waits for that
    task, not for the other variants reading the same folder (every variant reads `oracle_clean`'s
    points), so the variants' splats run side by side. Where no earlier task has run the method, the
    variant runs it, and writes its folder. A variant counts as having run its own method (`reconstruct`
    starts with it), not its points' method: it never gets to that one where its own method fails with
    anything but an alignment refusal (after a refusal it splats the denoised photos and does run its points'
    method). So where no base run is listed, later variants wait for the first one: docs/cluster.md.
    """
    ran: set[tuple[str, int, str]] = set()  # (scene, seed, method name) of the methods earlier tasks ran
    writes, reads = [], []
    for t in tasks:
        m, denoiser = t.method, t.config.denoiser
        if m.gt_pose_variant_of is None:
            writes.append(share_keys(t))
            reads.append(())
            ran.add((t.scene, t.seed, m.name))
            continue
        w: list[tuple[str, int, str]] = []
        r: list[tuple[str, int, str]] = []
        for needed in (m.gt_pose_variant_of, m.gt_pose_points_from):
            if needed is None:
                continue
            keys = [(t.scene, t.seed, f) for f in needed.runs_after(denoiser)]
            (r if (t.scene, t.seed, needed.name) in ran else w).extend(keys)
        ran.add((t.scene, t.seed, m.gt_pose_variant_of.name))
        writes.append(tuple(dict.fromkeys(w)))
        reads.append(tuple(dict.fromkeys(r)))
    return chain_after(writes, reads)


#: The parts of a run, in relative units, for the order the runs start in on a cluster
#: (`eval.distributed.submission_order`). Measured on DTU scan24 at sigma 25 (docs/bench/pipeline.md,
#: `runs/eval_s25_rule2*`): a round's alignment, splat and held-out scoring about 300 s (`instantsplat`,
#: 294-297 s), a learned denoiser about 450 s more (`product`, 746-752 s), a ground-truth-pose variant's own
#: splat and scoring about 350 s (`product@gt_poses` 1075-1087 s, its product's included), the scoring
#: alone a few seconds. Only their ratios matter.
ROUND_COST, LEARNED_DENOISER_COST, GT_SPLAT_COST, SCORING_COST = 1.0, 1.5, 1.2, 0.02


def _method_cost(method: EvalMethod, task: EvalTask, rounds_done: dict[tuple[str, int, str], int]) -> float:
    """The work of running `method` in `task`'s seed folder that `rounds_done` (folder key -> rounds an earlier
    run completed there) does not hold already; records what it adds."""
    denoiser = task.config.denoiser
    if method.gt_pose_variant_of is not None:  # its method and its points' method run first (`reconstruct`)
        before = [m for m in (method.gt_pose_variant_of, method.gt_pose_points_from) if m is not None]
        return GT_SPLAT_COST + sum(_method_cost(m, task, rounds_done) for m in before)
    if method.ground_truth_poses:
        return GT_SPLAT_COST
    rounds = method.pipeline_config(task.base, denoiser).rounds
    learned = MODEL_FILE in method.stages(task.dataset).denoise_outputs
    key = (task.scene, task.seed, method.folder(denoiser))
    have = rounds_done.get(key, 0)
    if method.shares_round1_with is not None:  # round 1 is linked in from that family's folder
        have = max(have, min(1, rounds_done.get((task.scene, task.seed, method.shares_round1_with), 0)))
    rounds_done[key] = max(have, rounds)
    return max(rounds - have, 0) * (ROUND_COST + (LEARNED_DENOISER_COST if learned else 0.0))


def expected_costs(tasks: Sequence[EvalTask]) -> list[float]:
    """Each task's expected cost, in `ROUND_COST` units: the rounds, denoiser and ground-truth-pose splat it
    runs that no earlier task (in the serial order) has run for it, plus its scoring (so every cost is
    positive: `eval.distributed.submission_order`)."""
    rounds_done: dict[tuple[str, int, str], int] = {}
    return [SCORING_COST + _method_cost(t.method, t, rounds_done) for t in tasks]


def evaluate_dataset(dataset: DatasetFolder, out: Path, config: EvalConfig, *, scene: str,
                     on_row: Callable[[list[RunScores]], None] | None = None,
                     executor: RayExecutor | None = None) -> list[RunScores]:
    """Run and score every method x seed on one dataset; returns one `RunScores` per run.

    `on_row(rows_so_far)` is called after each run (the CLI rewrites results.md, so an interrupted
    evaluation keeps what it measured).

    `executor` (`eval.distributed.ray_cluster`): the runs are Ray tasks, the writers of one folder
    (`task_graph`) in order, the others in parallel, the longest chains of runs started first
    (`expected_costs`); the rows come back in the serial order (seeds, then methods), and `on_row` gets
    the finished ones in that order. None: one after another here.

    Before any run, every file the evaluation (and `eval.results.write_results` into `out`) may replace is
    checked to be one it wrote (`check_eval_outputs`).

    Raises:
        InputError: dataset problems or settings a component does not have (found before any compute).
        UnownedOutputError: files in `out` that the evaluation would replace or delete but did not write, or
            that changed since (found before any run; raised by a run when they appear later).
        Any exception of a run other than `FAILED_RUN_ERRORS` (see `run_task`).
    """
    out = Path(out)
    gt = read_sparse_model(dataset.root / "sparse" / "0")
    missing = [n for n in dataset.train + dataset.test if n not in _stem_poses(gt)]
    if missing:
        raise InputError(f"views {missing} have no ground-truth camera", path=dataset.root / "sparse" / "0")
    k = config.views or min(12, len(dataset.train))
    # The dataset is at its working size already (`denoise-gs eval --max-size`, eval.pipeline.inputs):
    # the runs keep it, so renders and the clean images stay pixel-aligned.
    base = base_pipeline_config(config, k)
    methods = config.selected()
    for m in methods:  # a preset a component lacks fails here, before any compute
        check_settings(m.pipeline_config(base, config.denoiser))
    inputs = out / "inputs" / scene
    tasks = [EvalTask(scene, method, seed, dataset, base, inputs, out, config)
             for seed in config.seed_values for method in methods]
    check_eval_outputs(tasks)  # before anything is changed
    copy_train_inputs(dataset, inputs)
    save_heldout_references(out / HELDOUT_DIR / scene, dataset)
    if executor is not None:

        def finished(done: Mapping[int, RunScores]) -> None:
            if on_row is not None:
                on_row([done[i] for i in sorted(done)])

        return executor.run(run_task, tasks, after=task_graph(tasks),
                            cost=expected_costs(tasks), desc=f"eval {scene}", on_done=finished)
    rows: list[RunScores] = []
    for task in tasks:
        _log.info("eval %s: %s, seed %d", scene, task.method.name, task.seed)
        rows.append(run_task(task))
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

    A scene rendered before into the same folder is reused while its resolved scene (`scene.toml`) is this
    one and the renderer's code (`data_synth`, its source digest in `out/data/stages/<folder>.render.json`)
    is the code there is now; else it is rendered again (the folder is this command's own: `write_dataset`
    replaces only a dataset it wrote, unchanged). A render by the same code gives the same bytes, and the
    runs' inputs are compared by content, so rendering again changes nothing after it.
    """
    if kind == "dataset":
        return Path(source).name, Path(source)
    from data_synth import load_scene, scene_to_toml, write_dataset  # open3d: seconds to import, scenes only

    name = Path(source).stem if kind == "scene_file" else str(source)
    tag = "" if size_wh is None and views is None else f"_{size_wh[0]}x{size_wh[1]}" if size_wh else ""
    tag += f"_{views}v" if views is not None else ""
    folder = out / "data" / f"{name}{tag}"
    record = out / "data" / RECORD_DIR / f"{folder.name}.render.json"
    spec = load_scene(source, size_wh=size_wh, views=views)
    code = {"data_synth": source_digest("data_synth")}
    if (folder / "split.json").is_file():
        # Reused only while it is this scene: the file may have been edited since, or another scene file of the
        # same name given (the dataset's scene.toml is the resolved scene it was rendered from); and only while
        # the renderer is the code that rendered it (an edit of a degradation or the renderer changes the data).
        try:
            same = (folder / "scene.toml").read_text(encoding="utf-8") == scene_to_toml(spec)
            same_code = json.loads(record.read_text(encoding="utf-8")).get("code") == code
        except (OSError, UnicodeDecodeError, ValueError, AttributeError):
            same, same_code = False, False
        if same and same_code:
            return name, folder
        _log.warning("the %s rendered into %s before differs from the one now: rendering it again",
                     "scene" if not same else "renderer's code", folder)
    record.unlink(missing_ok=True)
    write_dataset(spec, folder, overwrite=folder.exists())
    atomic_write_text(record, json.dumps({"scene": str(source), "code": code}, indent=1))
    return name, folder

