"""`denoise-gs cost`: what accuracy costs in time (issue 8, deliver 4).

One knob of the pipeline is changed at a time from a base configuration (the
`fast` preset, one round, by default); each sweep point is a full
`run_pipeline` on the scene's noisy training images, scored like
`denoise-gs eval` (held-out PSNR/SSIM/LPIPS against the clean images after
Sim(3) registration and photometric pose refinement; training-pose rotation
error and ATE). Times are the stages' own wall seconds from the stage records
(so a stage reused from the cache reports the time it took when it ran), per
stage and summed end to end; scoring time is not included.

Reuse: every point runs in its own folder, first seeded with hard links to the
base point's completed stages, so the stage keys decide what re-runs (a
change of splat iterations re-runs splat and render only). Scores are cached
per point (`points/<name>/score.json`, committed with its record
`points/<name>/stages/score.json`), keyed by the final render stage's key and
the pose-fit setting.

The sweep changes only files it wrote: before any point runs, the results
(`eval.results.RESULTS_OUTPUTS`, written by `write_cost_results`), every
point's cached scores and the stage outputs of every point's run are checked
against their records; a file the sweep did not write, or one that changed
since, stops it (`UnownedOutputError`) with nothing changed.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from eval.distributed import chain_after
from eval.pipeline import PipelineConfig, PipelineStages, preset, product_stages, run_pipeline
from eval.pipeline.run import RUN_COMMAND, planned_run_outputs
from eval.pipeline.stage import OwnershipCheck, check_outputs_owned, commit_written
from eval.pipeline.stage_settings import check_settings, round_settings
from eval.pipeline.validate import DatasetFolder
from eval.results import RESULTS_OUTPUTS, RESULTS_RECORD, check_results_owned, save_figure
from mvgeo.common.atomic import atomic_write_text
from mvgeo.common.errors import InputError
from mvgeo.common.output import prepare_output, write_manifest

if TYPE_CHECKING:
    from eval.distributed import RayExecutor

__all__ = ["DEFAULT_GRID", "KNOBS", "SCORE_FILE", "SCORE_RECORD", "CostConfig", "CostPoint", "SweepPoint",
           "apply_knob", "check_cost_outputs", "run_cost_sweep", "sweep_points", "write_cost_results"]

_log = logging.getLogger(__name__)

#: A point's cached scores in its folder, and the name of their record (`points/<name>/stages/<name>.json`).
SCORE_FILE = "score.json"
SCORE_RECORD = "score"


def _set_denoise(cfg: PipelineConfig, **kw) -> PipelineConfig:
    return dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, **kw))


def _set_align(cfg: PipelineConfig, **kw) -> PipelineConfig:
    return dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, **kw))


def _set_splat(cfg: PipelineConfig, **kw) -> PipelineConfig:
    return dataclasses.replace(cfg, splat=dataclasses.replace(cfg.splat, **kw))


def _set_preset(cfg: PipelineConfig, name: object) -> PipelineConfig:
    new = preset(str(name), views=cfg.views, seed=cfg.seed, device=cfg.device)  # the preset's own rounds
    return _set_align(new, max_focal_log_std=cfg.align.max_focal_log_std)  # keep the sweep's focal policy


#: knob -> (what it changes, how). `train_views` is handled by the sweep (a subset of the images).
KNOBS: dict[str, tuple[str, Callable[[PipelineConfig, object], PipelineConfig]]] = {
    "n2v_steps": ("N2V training steps (round 1)", lambda c, v: _set_denoise(c, n2v_steps=int(v))),
    "passes": ("N2V inference passes K", lambda c, v: _set_denoise(c, passes=int(v))),
    "align_iters": ("global-alignment iterations", lambda c, v: _set_align(c, iters=int(v))),
    "align_size": ("alignment image size (long side, px)", lambda c, v: _set_align(c, max_size_px=int(v))),
    "align_points": ("output point budget of the alignment (the splat's initial Gaussians)",
                     lambda c, v: _set_align(c, points=int(v))),
    "splat_iters": ("splat training iterations", lambda c, v: _set_splat(c, iters=int(v))),
    "views": ("K views kept for round 2 (2 rounds)",
              lambda c, v: dataclasses.replace(c, views=int(v), rounds=2)),
    "train_views": ("number of noisy training images", lambda c, v: c),
    "preset": ("pipeline preset (its own rounds)", _set_preset),
}

#: The default sweep (values around the `fast` preset; each point is one pipeline run at the sweep's size).
DEFAULT_GRID: dict[str, tuple] = {
    "n2v_steps": (100, 400, 1000),
    "passes": (1, 2, 8),
    "align_iters": (25, 100, 300),
    "align_size": (64, 96, 128),
    "align_points": (20_000, 40_000),
    "splat_iters": (100, 300, 1000),
    "views": (4, 8),
    "train_views": (4, 6, 8),
    "preset": ("fast", "default"),
}


@dataclass(frozen=True)
class SweepPoint:
    """One pipeline configuration of the sweep.

    Attributes:
        knob, value: what was changed from the base ("base", None for the base itself).
        config: the pipeline configuration.
        train_views: number of training images used (None: all).
    """

    knob: str
    value: object
    config: PipelineConfig
    train_views: int | None = None

    @property
    def name(self) -> str:
        return "base" if self.knob == "base" else f"{self.knob}={self.value}"


def apply_knob(base: PipelineConfig, knob: str, value: object) -> PipelineConfig:
    """`base` with `knob` set to `value`.

    Raises:
        InputError: unknown knob or a value the pipeline config rejects.
    """
    if knob not in KNOBS:
        raise InputError(f"unknown knob {knob!r}", fix=f"choose from {', '.join(KNOBS)}")
    try:
        return KNOBS[knob][1](base, value)
    except (ValueError, TypeError) as exc:
        raise InputError(f"bad value {value!r} for knob {knob}: {exc}") from exc


def sweep_points(base: PipelineConfig, grid: Mapping[str, Sequence[object]]) -> list[SweepPoint]:
    """The base point, then one point per (knob, value), in grid order.

    Raises:
        InputError: unknown knob, empty value list or a bad value (before any compute).
    """
    points = [SweepPoint("base", None, base)]
    for knob, values in grid.items():
        if not len(values):
            raise InputError(f"knob {knob} has no values")
        for v in values:
            if knob == "train_views":
                if int(v) < 2:
                    raise InputError(f"train_views must be >= 2, got {v}")
                points.append(SweepPoint(knob, int(v), base, train_views=int(v)))
            else:
                points.append(SweepPoint(knob, v, apply_knob(base, knob, v)))
    return points


@dataclass(frozen=True)
class CostConfig:
    """Settings of `run_cost_sweep`.

    Attributes:
        base: the base pipeline configuration (default: `fast`, 1 round, K = 8).
        grid: knob -> values (default `DEFAULT_GRID`).
        pose_fit_iters: held-out pose refinement steps (None: `splat`'s default).
    """

    base: PipelineConfig = field(default_factory=lambda: preset("fast", rounds=1, views=8))
    grid: Mapping[str, Sequence[object]] = field(default_factory=lambda: dict(DEFAULT_GRID))
    pose_fit_iters: int | None = None


@dataclass(frozen=True)
class CostPoint:
    """Measured cost and accuracy of one sweep point.

    Attributes:
        name, knob, value: identify the point.
        stage_s: stage label (`roundN/stage`) -> wall seconds when it ran.
        total_s: sum of `stage_s` (end to end, scoring excluded).
        psnr_db, ssim, lpips: held-out means against the clean images.
        rot_err_deg, ate: training-pose errors: the median relative rotation error over the pairs of views,
            and the ATE after Sim(3).
    """

    name: str
    knob: str
    value: object
    stage_s: dict[str, float]
    total_s: float
    psnr_db: float
    ssim: float
    lpips: float
    rot_err_deg: float
    ate: float


def _share_stages(src: Path, dst: Path) -> None:
    """Seed a new point folder with hard links to `src`'s round folders (keys decide what re-runs)."""
    if os.path.lexists(dst) or not src.is_dir():
        return
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.link-", dir=dst.parent))

    def link(a: str, b: str) -> None:
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    try:
        for rd in sorted(src.glob("round*")):
            shutil.copytree(rd, tmp / rd.name, copy_function=link,
                            ignore=lambda d, names: [n for n in names if n.startswith(".")])
        write_manifest(tmp, RUN_COMMAND, record_files=False)  # a run folder: `run_pipeline` resumes into it
        os.replace(tmp, dst)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # gone after the rename; this call's own folder otherwise


def _subset(names: Sequence[str], n: int) -> list[str]:
    """`n` of `names`, evenly spaced (first and last kept)."""
    if n >= len(names):
        return list(names)
    idx = np.unique(np.round(np.linspace(0, len(names) - 1, n)).astype(int))
    return [names[i] for i in idx]


def _inputs_folder(dataset: DatasetFolder, folder: Path, names: Sequence[str]) -> Path:
    """`folder` holding hard links to the noisy training images `names` (rebuilt if different)."""
    from eval.evaluate import copy_train_inputs

    return copy_train_inputs(dataset, folder, names)


def run_cost_sweep(dataset: DatasetFolder, out: Path, config: CostConfig, *,
                   score: Callable | None = None, stages: PipelineStages | None = None,
                   executor: RayExecutor | None = None) -> list[CostPoint]:
    """Run and score every sweep point on `dataset`.

    Args:
        dataset: a checked dataset folder (noisy training images, held-out clean images, GT cameras).
        out: the sweep folder (`out/points/<name>/` per point, `out/inputs*/`).
        config: base configuration, grid and pose-fit setting.
        score: ``score(final_round_dir, dataset, train_names) -> dict`` with the keys of
            `CostPoint`'s metrics; default `eval.evaluate.score_reconstruction` (tests pass a cheap one).
        stages: pipeline stage functions (default the product's; tests pass small real ones).
        executor: run the points as Ray tasks (`eval.distributed.ray_cluster`): the base point first,
            then the others in parallel; the rows come back in the serial order. None: one after another.

    Raises:
        InputError: bad grid values, or a preset a component does not have (before any compute).
        UnownedOutputError: files in `out` the sweep would replace or delete but did not write, or that
            changed since (`check_cost_outputs`, before any compute; nothing is changed).
    """
    from eval.evaluate import score_reconstruction

    out = Path(out)
    points = sweep_points(config.base, config.grid)
    for p in points:
        check_settings(p.config)
    n_train = len(dataset.train)
    beyond = [p.name for p in points if p.train_views is not None and p.train_views > n_train]
    if beyond:  # such a point would use every view under another count's label; `denoise-gs cost` refuses a
        # value the user gave in --grid before any compute, the default grid's are left out here
        _log.warning("the dataset has %d training views: %s left out of the sweep", n_train, ", ".join(beyond))
        points = [p for p in points if p.name not in beyond]
    if score is None:
        score = lambda rd, ds, names: score_reconstruction(  # noqa: E731
            rd, ds, names, pose_fit_iters=config.pose_fit_iters, device=config.base.device)
    jobs = [_PointJob(p, dataset, out, config.pose_fit_iters, score, stages) for p in points]
    check_cost_outputs(out, jobs)  # before anything is changed
    if executor is not None:
        for job in jobs:  # here, before the tasks: points with the same images share the folder
            _inputs_folder(dataset, out / f"inputs{job.tag}", job.names)
        # A point linked to the base point's stages waits for it; a repeated point for its first run.
        keys = [(job.point.name,) for job in jobs]
        after = [tuple(sorted({*a, *((0,) if i and job.shares_base else ())}))
                 for i, (job, a) in enumerate(zip(jobs, chain_after(keys), strict=True))]
        return executor.run(_run_point, jobs, after=after, desc="cost sweep")
    return [_run_point(job) for job in jobs]


@dataclass(frozen=True)
class _PointJob:
    """One sweep point to run and score: the argument of `_run_point` (picklable, to run as a task)."""

    point: SweepPoint
    dataset: DatasetFolder
    out: Path
    pose_fit_iters: int | None
    score: Callable
    stages: PipelineStages | None

    @property
    def names(self) -> list[str]:
        """The training images it uses."""
        train = self.dataset.train
        return _subset(train, self.point.train_views) if self.point.train_views else list(train)

    @property
    def tag(self) -> str:
        """Suffix of its inputs folder: "" for all training images."""
        return "" if self.point.train_views is None or len(self.names) == len(self.dataset.train) \
            else f"_{len(self.names)}"

    @property
    def shares_base(self) -> bool:
        """Its folder starts from links to the base point's stages."""
        return self.point.name != "base" and not self.tag


def check_cost_outputs(out: Path, jobs: Sequence[_PointJob]) -> None:
    """Check, before any point runs, that the sweep into `out` would replace or delete only files it wrote:
    the results (`eval.results.check_results_owned`), each point's cached scores (`SCORE_FILE`) and the
    stage outputs its run may write (as `run_pipeline` checks them); and that each point's folder can be
    opened as a run folder (`prepare_output`). One error names every file found.

    Raises:
        UnownedOutputError: files the sweep did not write, or that changed since, where it writes.
        InputError: a point's folder is refused as a whole (e.g. a folder of the user's at its path).
    """
    owned = OwnershipCheck()
    check = owned.check
    check(check_results_owned, out)
    for job in jobs:
        run_dir = out / "points" / job.point.name
        prepare_output(run_dir, command=RUN_COMMAND, resume=True)
        check(check_outputs_owned, run_dir, SCORE_RECORD, (SCORE_FILE,))
        stages = job.stages if job.stages is not None else product_stages()
        settings = [round_settings(job.point.config, r) for r in range(1, job.point.config.rounds + 1)]
        for stage_dir, name, outputs in planned_run_outputs(run_dir, stages, settings):
            check(check_outputs_owned, stage_dir, name, outputs, defer_hidden=True)
    owned.raise_if_any(out)


def _cached_scores(cache: Path, key: Mapping[str, object]) -> dict[str, float] | None:
    """The metrics `cache` holds for `key`, None when it holds another key's.

    Raises:
        InputError: `cache` is not the JSON object of scores `_run_point` writes.
    """
    if not cache.is_file():
        return None
    try:
        rec = json.loads(cache.read_text(encoding="utf-8"))
        if not isinstance(rec, dict):
            raise ValueError(f"it holds a {type(rec).__name__}, not an object")
        if rec.get("key") != key:
            return None
        return {str(k): float(v) for k, v in dict(rec["metrics"]).items()}
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, RecursionError) as exc:
        why = "JSON nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise InputError(f"the point's cached scores cannot be read ({why})", path=cache,
                         fix="move the file out of the sweep folder (the point is scored again), or choose "
                             "another --out") from None


def _run_point(job: _PointJob) -> CostPoint:
    """Run (or resume) one sweep point in `out/points/<name>/` and score it (scores cached per point; they are
    checked to be the sweep's own first).

    Raises:
        UnownedOutputError: the point's folder holds files the sweep did not write or that changed since.
    """
    p, dataset, out = job.point, job.dataset, job.out
    names, tag = job.names, job.tag
    run_dir = out / "points" / p.name
    check_outputs_owned(run_dir, SCORE_RECORD, (SCORE_FILE,))
    inputs = _inputs_folder(dataset, out / f"inputs{tag}", names)
    if job.shares_base:
        _share_stages(out / "points" / "base", run_dir)
    _log.info("cost sweep: %s", p.name)
    res = run_pipeline(inputs, run_dir, p.config, stages=job.stages)
    ran = [*res.rounds, *([res.stopped] if res.stopped is not None else [])]
    stage_s = {f"round{r.index}/{n}": float(s.seconds) for r in ran for n, s in r.stages.items()}
    final = res.rounds[-1]
    key = {"render": final.stages["render"].key, "pose_fit_iters": job.pose_fit_iters,
           "test": list(dataset.test)}
    metrics = _cached_scores(run_dir / SCORE_FILE, key)
    if metrics is None:
        metrics = {k: float(v) for k, v in dict(job.score(final.dir, dataset, names)).items()}
        text = json.dumps({"key": key, "metrics": metrics}, indent=2) + "\n"
        commit_written(run_dir, SCORE_RECORD, (SCORE_FILE,), lambda work: atomic_write_text(work / SCORE_FILE, text))
    return CostPoint(p.name, p.knob, p.value, stage_s, float(sum(stage_s.values())),
                     **{k: metrics.get(k, float("nan")) for k in ("psnr_db", "ssim", "lpips", "rot_err_deg", "ate")})


# ----------------------------------------------------------------- reporting
def _f(x: float, digits: int) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def cost_markdown(rows: Sequence[CostPoint], *, title: str) -> str:
    """One table per knob (base point first), then the figures."""
    base = next((r for r in rows if r.knob == "base"), None)
    lines = [f"# {title}", "",
             "Held-out views against the clean images; times are the stages' wall seconds (end to end = their sum, "
             "scoring excluded). One knob changes at a time from the base point; one seed, so differences of a "
             "few tenths of a dB are within run-to-run spread.", ""]
    stage_names = list(dict.fromkeys(s for r in rows for s in r.stage_s))
    for knob in dict.fromkeys(r.knob for r in rows):
        label = "base configuration" if knob == "base" else f"{knob}: {KNOBS[knob][0]}"
        lines += [f"## {label}", "", "| value | PSNR (dB) | SSIM | LPIPS | rot. err. median (deg) | ATE | "
                  "end to end (s) | slowest stages (s) |", "|---|---|---|---|---|---|---|---|"]
        knob_rows = [r for r in rows if r.knob == knob]
        for r in knob_rows:
            top = sorted(r.stage_s.items(), key=lambda kv: -kv[1])[:3]
            stages = ", ".join(f"{k} {v:.0f}" for k, v in top)
            lines.append(f"| {r.value if knob != 'base' else 'base'} | {_f(r.psnr_db, 2)} | {_f(r.ssim, 3)} | "
                         f"{_f(r.lpips, 3)} | {_f(r.rot_err_deg, 2)} | {_f(r.ate, 3)} | {r.total_s:.0f} | {stages} |")
        lines.append("")
    if base is not None:
        lines += ["## Base point, seconds per stage", "", "| stage | s |", "|---|---|"]
        lines += [f"| {s} | {base.stage_s.get(s, float('nan')):.1f} |" for s in stage_names if s in base.stage_s]
        lines.append("")
    return "\n".join(lines)


def plot_cost(rows: Sequence[CostPoint], folder: Path) -> list[Path]:
    """`psnr_vs_time.png` and `pose_vs_time.png` (one panel per knob, end-to-end seconds on x) and
    `stage_times.png` (stacked seconds per stage and point)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    knobs = [k for k in dict.fromkeys(r.knob for r in rows) if k != "base"]
    base = next((r for r in rows if r.knob == "base"), None)
    paths = []
    for metric, label, fname in (("psnr_db", "held-out PSNR (dB)", "psnr_vs_time.png"),
                                 ("rot_err_deg", "training rotation error, median (deg)", "pose_vs_time.png")):
        n = max(1, len(knobs))
        cols = min(4, n)
        nrows = (n + cols - 1) // cols
        fig, axes = plt.subplots(nrows, cols, figsize=(3.2 * cols, 2.6 * nrows), dpi=110, squeeze=False)
        for ax, knob in zip(axes.flat, knobs, strict=False):
            pts = [r for r in rows if r.knob == knob]
            xs = [r.total_s for r in pts]
            ys = [getattr(r, metric) for r in pts]
            ax.plot(xs, ys, "o-")
            for r, x, y in zip(pts, xs, ys, strict=True):
                ax.annotate(str(r.value), (x, y), fontsize=7, textcoords="offset points", xytext=(3, 3))
            if base is not None:
                ax.plot([base.total_s], [getattr(base, metric)], "k*", ms=8)
            ax.set_title(knob, fontsize=8)
            ax.set_xlabel("end to end (s)", fontsize=7)
            ax.set_ylabel(label, fontsize=7)
            ax.tick_params(labelsize=7)
        for ax in list(axes.flat)[len(knobs):]:
            ax.axis("off")
        fig.tight_layout()
        save_figure(fig, folder / fname)
        plt.close(fig)
        paths.append(folder / fname)
    stages = list(dict.fromkeys(s for r in rows for s in r.stage_s))
    fig, ax = plt.subplots(figsize=(max(5.0, 0.35 * len(rows) + 2), 3.2), dpi=110)
    bottom = np.zeros(len(rows))
    for s in stages:
        vals = np.array([r.stage_s.get(s, 0.0) for r in rows])
        ax.bar(np.arange(len(rows)), vals, bottom=bottom, label=s)
        bottom += vals
    ax.set_xticks(np.arange(len(rows)), [r.name for r in rows], rotation=70, fontsize=6, ha="right")
    ax.set_ylabel("seconds")
    ax.legend(fontsize=6, ncols=2)
    fig.tight_layout()
    save_figure(fig, folder / "stage_times.png")
    plt.close(fig)
    paths.append(folder / "stage_times.png")
    return paths


def write_cost_results(out: Path, rows: Sequence[CostPoint], *, title: str) -> tuple[Path, Path]:
    """`results.json`, `results.md` and `figures/*.png` in `out`, committed with their record like
    `eval.results.write_results` (`RESULTS_OUTPUTS`, `RESULTS_RECORD`).

    Raises:
        UnownedOutputError: those files in `out` include some it did not write or that changed (nothing is
            replaced).
    """
    out = Path(out)

    def safe(x: object) -> object:
        return None if isinstance(x, float) and not np.isfinite(x) else x

    def write(dest: Path) -> None:
        data = [{k: (safe(v) if not isinstance(v, dict) else v) for k, v in dataclasses.asdict(r).items()}
                for r in rows]
        atomic_write_text(dest / "results.json", json.dumps({"points": data}, indent=2, default=str) + "\n")
        figs = plot_cost(rows, dest / "figures")
        md = cost_markdown(rows, title=title)
        md += "\n## Figures\n\n" + "\n".join(f"![{p.stem}]({p.relative_to(dest).as_posix()})" for p in figs) + "\n"
        atomic_write_text(dest / "results.md", md)

    commit_written(out, RESULTS_RECORD, RESULTS_OUTPUTS, write)
    return out / "results.json", out / "results.md"
