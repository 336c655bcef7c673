"""Evaluation results: per-run rows, mean +- std over seeds, `results.json`, `results.md`, bar charts.

The files `denoise-gs eval` and `denoise-gs cost` write at the top of their output folder
(`RESULTS_OUTPUTS`) are committed like a pipeline stage's outputs (`eval.pipeline.stage.commit_written`):
written in a hidden work folder, then renamed into place, with a record `OUT/stages/results.json` of every
file. A later invocation replaces only files that record lists with
their recorded content; anything else there (a note added to `results.md`, a file put in `figures/`)
stops it with `UnownedOutputError` and nothing is changed. A file is always replaced by a rename, never
written into, so hard and symbolic links at an output's path keep what they point to.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from eval.pipeline.stage import check_outputs_owned, commit_written
from mvgeo.common.atomic import atomic_write_bytes, atomic_write_text

__all__ = ["METRICS", "RESULTS_OUTPUTS", "RESULTS_RECORD", "CarriedRows", "RunScores", "SummaryCell",
           "carried_rows", "check_results_owned", "merge_rows", "plot_bars", "results_markdown", "save_figure",
           "summarise", "write_results"]

#: What `write_results` (and `eval.cost.write_cost_results`) write in OUT, and the name of their record
#: (`OUT/stages/<name>.json`).
RESULTS_OUTPUTS = ("results.json", "results.md", "figures")
RESULTS_RECORD = "results"

#: metric -> (label, higher is better)
METRICS: dict[str, tuple[str, bool]] = {
    "psnr_db": ("PSNR (dB)", True),
    "ssim": ("SSIM", True),
    "lpips": ("LPIPS", False),
    "rot_err_deg": ("rot. err. median (deg)", False),
    "ate": ("ATE (GT units)", False),
    "seconds": ("time (s)", False),
}


@dataclass(frozen=True)
class RunScores:
    """One method on one scene with one seed; held-out image metrics are means over held-out views.

    Attributes:
        scene, method, seed: identify the run.
        psnr_db, ssim, lpips: held-out views against the clean images.
        rot_err_deg: median relative rotation error over the pairs of training views (NaN when poses are given).
        ate: absolute trajectory error of the training camera centres after Sim(3), GT units (NaN when given).
        seconds: end-to-end wall time of the method (pipeline methods: the sum of their stages' recorded
            times, stages reused from the cache included).
        per_view: held-out view -> {"psnr_db", "ssim", "lpips"}.
        error: why the run failed ("" when it did not); its metrics are then NaN.
    """

    scene: str
    method: str
    seed: int
    psnr_db: float
    ssim: float
    lpips: float
    rot_err_deg: float = float("nan")
    ate: float = float("nan")
    seconds: float = float("nan")
    per_view: dict[str, dict[str, float]] = field(default_factory=dict)
    error: str = ""


@dataclass(frozen=True)
class SummaryCell:
    """Mean and sample standard deviation over seeds (std NaN for one seed; NaNs ignored)."""

    mean: float
    std: float
    n: int

    def format(self, digits: int) -> str:
        if self.n == 0:
            return "n/a"
        if self.n == 1 or math.isnan(self.std):
            return f"{self.mean:.{digits}f}"
        return f"{self.mean:.{digits}f} ± {self.std:.{digits}f}"


def _cell(values: Sequence[float]) -> SummaryCell:
    v = np.asarray([x for x in values if not math.isnan(x)], np.float64)
    if v.size == 0:
        return SummaryCell(float("nan"), float("nan"), 0)
    return SummaryCell(float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else float("nan"), int(v.size))


def summarise(rows: Sequence[RunScores]) -> dict[str, dict[str, dict[str, SummaryCell]]]:
    """scene -> method -> metric -> `SummaryCell`, methods in first-seen order."""
    out: dict[str, dict[str, dict[str, SummaryCell]]] = {}
    groups: dict[tuple[str, str], list[RunScores]] = {}
    for r in rows:
        groups.setdefault((r.scene, r.method), []).append(r)
    for (scene, method), rs in groups.items():
        out.setdefault(scene, {})[method] = {m: _cell([getattr(r, m) for r in rs]) for m in METRICS}
    return out


_DIGITS = {"psnr_db": 2, "ssim": 3, "lpips": 3, "rot_err_deg": 2, "ate": 4, "seconds": 0}


def _scene_seeds(rows: Sequence[RunScores], scene: str) -> int:
    """How many seeds `scene` was run with (failed runs included)."""
    return len({r.seed for r in rows if r.scene == scene})


def _valid_seeds(rows: Sequence[RunScores], scene: str, method: str, metric: str) -> frozenset[int]:
    """The seeds of `method`'s rows in `scene` whose `metric` is a number (its cell's values)."""
    return frozenset(r.seed for r in rows if r.scene == scene and r.method == method
                     and not math.isnan(getattr(r, metric)))


def results_markdown(rows: Sequence[RunScores], *, title: str = "Evaluation") -> str:
    """Per-scene tables, mean ± std over seeds, best value per column in bold.

    A cell is the mean over the seeds its method has a value for: a failed run (NaN) is left out of it, and
    the runs are listed under the table. A cell over fewer seeds than the scene was run with says so
    ("(2 of 3 seeds)"), and a column's best value is bold only where every cell of it is over the same seeds:
    a method that failed on the hard seeds would otherwise be ranked on the easy ones only.
    """
    summary = summarise(rows)
    lines = [f"# {title}", "", "Held-out views scored against the clean images; mean ± sample std over seeds "
             "(a cell over fewer seeds than its scene's, a failed run left out, says how many; the best value is "
             "bold only in a column whose cells are all over the same seeds). Training-pose errors after Sim(3) "
             "registration to ground truth.", ""]
    for scene, methods in summary.items():
        seeds = _scene_seeds(rows, scene)
        lines += [f"## {scene} ({seeds} seed(s))", "",
                  "| method | " + " | ".join(lbl for lbl, _ in METRICS.values()) + " |",
                  "|---" * (len(METRICS) + 1) + "|"]
        best = {}
        for m, (_, higher) in METRICS.items():
            vals = [c[m].mean for c in methods.values() if c[m].n]
            same_seeds = len({_valid_seeds(rows, scene, method, m) for method, c in methods.items() if c[m].n}) == 1
            if vals and m != "seconds" and same_seeds:
                best[m] = max(vals) if higher else min(vals)
        for method, cells in methods.items():
            row = []
            for m in METRICS:
                text = cells[m].format(_DIGITS[m])
                if 0 < cells[m].n < seeds:
                    text += f" ({cells[m].n} of {seeds} seeds)"
                if m in best and cells[m].n and cells[m].mean == best[m] and len(methods) > 1:
                    text = f"**{text}**"
                row.append(text)
            lines.append(f"| {method} | " + " | ".join(row) + " |")
        lines.append("")
        failed = [r for r in rows if r.scene == scene and r.error]
        if failed:
            lines += ["Failed runs (left out of the means above):", ""]
            lines += [f"- {r.method}, seed {r.seed}: {r.error[:300]}" for r in failed]
            lines.append("")
    return "\n".join(lines)


def seed_shortfalls(rows: Sequence[RunScores], metric: str) -> dict[tuple[str, str], str]:
    """(scene, method) -> "n/N" where `method`'s `metric` in `scene` is a mean over fewer seeds (n) than the
    scene was run with (N; a failed run is left out of its mean)."""
    out = {}
    for scene, methods in summarise(rows).items():
        seeds = _scene_seeds(rows, scene)
        for method, cells in methods.items():
            if 0 < cells[metric].n < seeds:
                out[(scene, method)] = f"{cells[metric].n}/{seeds}"
    return out


def plot_bars(rows: Sequence[RunScores], path: Path, *, metric: str = "psnr_db") -> Path:
    """Bar chart of `metric` per method (error bars: std over seeds), one group per scene; PNG.

    A bar over fewer seeds than its scene's (a failed run left out; `seed_shortfalls`) is hatched and labelled
    with its seed count ("2/3"), as its cell in results.md says."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = summarise(rows)
    short = seed_shortfalls(rows, metric)
    scenes = list(summary)
    methods = list(dict.fromkeys(m for s in summary.values() for m in s))
    width = 0.8 / max(1, len(methods))
    fig, ax = plt.subplots(figsize=(max(4.0, 1.6 * len(scenes) * max(1, len(methods)) ** 0.5), 3.2), dpi=120)
    for j, method in enumerate(methods):
        means = [summary[s][method][metric].mean if method in summary[s] else np.nan for s in scenes]
        stds = [summary[s][method][metric].std if method in summary[s] else np.nan for s in scenes]
        x = np.arange(len(scenes)) + (j - (len(methods) - 1) / 2) * width
        bars = ax.bar(x, means, width, yerr=np.nan_to_num(stds), capsize=2, label=method)
        for k, scene in enumerate(scenes):
            if (scene, method) in short:
                bars[k].set_hatch("//")
                ax.text(x[k], means[k], short[(scene, method)], ha="center", va="bottom", fontsize=6)
    ax.set_xticks(np.arange(len(scenes)), scenes)
    ax.set_ylabel(METRICS[metric][0])
    ax.legend(fontsize=7, ncols=2)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path


def plot_heldout_grid(folder: Path, path: Path, *, seed: int = 0, max_views: int = 3,
                      methods: Sequence[str] | None = None) -> Path | None:
    """Grid of held-out views (rows) x clean | noisy | each method's render (columns), one seed; PNG.

    Reads what `eval.evaluate.save_heldout_renders` kept under `folder` (one scene); None when
    nothing is there. `methods` orders the columns (default: the saved methods by name); methods
    without saved renders are left out. Each method cell is titled with its PSNR against the clean image.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mvgeo.common.imageio import read_image

    folder = Path(folder)
    clean_dir = folder / "_clean"
    if not clean_dir.is_dir():
        return None
    views = sorted(p.stem for p in clean_dir.glob("*.png"))[:max_views]
    saved = sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith("_")
                   and (p / f"seed{seed}").is_dir())
    methods = saved if methods is None else [m for m in methods if m in saved]
    cols = ["_clean", "_noisy", *methods]
    if not views or not methods:
        return None
    fig, axes = plt.subplots(len(views), len(cols), figsize=(2.2 * len(cols), 1.8 * len(views)), dpi=120,
                             squeeze=False)
    for r, v in enumerate(views):
        clean = read_image(clean_dir / f"{v}.png")
        for c, col in enumerate(cols):
            ax = axes[r][c]
            ax.axis("off")
            f = folder / col / f"{v}.png" if col.startswith("_") else folder / col / f"seed{seed}" / f"{v}.png"
            if not f.is_file():
                continue
            img = read_image(f)
            ax.imshow(np.clip(img, 0.0, 1.0))
            title = col.strip("_") if col.startswith("_") else col
            if col != "_clean" and img.shape == clean.shape:
                title += f"\n{10 * np.log10(1.0 / max(float(np.mean((img - clean) ** 2)), 1e-12)):.2f} dB"
            ax.set_title(f"{v}: {title}" if c == 0 else title, fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path


def _json_safe(x: object) -> object:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_safe(v) for v in x]
    return x


def save_figure(fig: Any, path: Path) -> Path:
    """Save a matplotlib figure to `path` (format from its suffix, PNG without one) through a temporary
    sibling renamed onto it: an existing file is replaced, never written into, so a hard link to it or a
    symbolic link at `path` keeps what it points to. Returns `path`."""
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".").lower() or "png")
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def check_results_owned(out: Path) -> None:
    """Raise `UnownedOutputError` when `RESULTS_OUTPUTS` in `out` hold files `write_results` (or
    `eval.cost.write_cost_results`) did not write there, or that changed since; without a record (a
    folder written before the record existed) every such file counts as not written by the command."""
    check_outputs_owned(Path(out), RESULTS_RECORD, RESULTS_OUTPUTS)


def write_results(out: Path, rows: Sequence[RunScores], *, title: str = "Evaluation",
                  settings: Mapping[str, Any] | None = None) -> tuple[Path, Path]:
    """Write `results.json` (rows + summary; NaN -> null), `results.md` and `figures/<metric>.png` into `out`
    (committed with a record, see the module docstring).

    Args:
        settings: JSON-able description of what produced the rows (the evaluation's settings and the code's
            digest), stored in `results.json` as "settings"; `carried_rows` keeps rows of an earlier
            invocation only when it matches.

    Raises:
        UnownedOutputError: those files in `out` include some it did not write or that changed (nothing is
            replaced).
    """
    out = Path(out)
    commit_written(out, RESULTS_RECORD, RESULTS_OUTPUTS,
                   lambda work: _write_result_files(out, work, rows, title, settings))
    return out / "results.json", out / "results.md"


@dataclass(frozen=True)
class CarriedRows:
    """What `carried_rows` keeps of an earlier invocation's `results.json`.

    Attributes:
        rows: its rows for runs the new invocation does not make, in their order.
        note: why nothing was kept although there were rows ("" when everything eligible was kept, or there
            was nothing to keep).
    """

    rows: tuple[RunScores, ...]
    note: str = ""


def carried_rows(out: Path, settings: Mapping[str, Any], rerun: Collection[tuple[str, str, int]]) -> CarriedRows:
    """The rows of an earlier `denoise-gs eval` into `out` that its tables keep beside this invocation's.

    An evaluation into an existing folder (e.g. one method now, another later; its stages are reused) extends
    the earlier table instead of replacing it, but only when the earlier rows come from the same settings
    (`settings`, compared as stored: the dataset, the preset and every option that changes a score, and the
    project code's digest); otherwise they would not be comparable and none are kept (`note` says why).
    Rows whose (scene, method, seed) is in `rerun` are left out: this invocation writes them anew.
    """
    path = Path(out) / "results.json"
    if not path.is_file():
        return CarriedRows(())
    try:
        data = json.loads(path.read_text())
        runs = data.get("runs", [])
        before = data.get("settings")
        rows = tuple(_row_from_json(r) for r in runs)
    except (OSError, ValueError, TypeError, AttributeError, KeyError) as exc:
        return CarriedRows((), f"{path} could not be read ({exc}); its rows are not kept")
    if not rows:
        return CarriedRows(())
    if before != _json_safe(dict(settings)):
        changed = sorted(k for k in set(before or {}) | set(settings)
                         if (before or {}).get(k) != _json_safe(settings.get(k)))
        why = "it records no settings" if before is None else "its settings differ: " + ", ".join(changed)
        return CarriedRows((), f"the {len(rows)} earlier row(s) in {path} are not kept ({why}); evaluate "
                               f"into another --out to keep both")
    rerun = set(rerun)
    return CarriedRows(tuple(r for r in rows if (r.scene, r.method, r.seed) not in rerun))


def merge_rows(earlier: Sequence[RunScores], rows: Sequence[RunScores]) -> list[RunScores]:
    """`earlier` rows without the runs `rows` holds, then `rows`: one row per (scene, method, seed)."""
    new = {(r.scene, r.method, r.seed) for r in rows}
    return [r for r in earlier if (r.scene, r.method, r.seed) not in new] + list(rows)


_FLOAT_FIELDS = {f.name for f in fields(RunScores) if f.type in ("float", float)}


def _row_from_json(d: Mapping[str, Any]) -> RunScores:
    """A `RunScores` from its `results.json` form (null -> NaN, the per-view metrics included)."""
    def num(x: Any) -> float:
        return float("nan") if x is None else float(x)

    known = {f.name for f in fields(RunScores)}
    kw = {k: (num(v) if k in _FLOAT_FIELDS else v) for k, v in d.items() if k in known}
    kw["per_view"] = {v: {m: num(x) for m, x in ms.items()} for v, ms in (d.get("per_view") or {}).items()}
    kw["seed"] = int(d["seed"])
    return RunScores(**kw)


def _write_result_files(out: Path, dest: Path, rows: Sequence[RunScores], title: str,
                        settings: Mapping[str, Any] | None) -> None:
    """The results of the evaluation in `out` (held-out renders read from `out/heldout/`), written into `dest`."""
    summary = {s: {m: {k: asdict(c) for k, c in cells.items()} for m, cells in ms.items()}
               for s, ms in summarise(rows).items()}
    json_path, md_path = dest / "results.json", dest / "results.md"
    content: dict[str, Any] = {"runs": [asdict(r) for r in rows], "summary": summary}
    if settings is not None:
        content["settings"] = dict(settings)
    atomic_write_text(json_path, json.dumps(_json_safe(content), indent=2) + "\n")
    md = results_markdown(rows, title=title)
    figs = []
    for metric in ("psnr_db", "ssim", "lpips"):
        figs.append(plot_bars(rows, dest / "figures" / f"{metric}.png", metric=metric))
    for scene in dict.fromkeys(r.scene for r in rows):
        grid = plot_heldout_grid(out / "heldout" / scene, dest / "figures" / f"heldout_{scene}.png",
                                 methods=list(dict.fromkeys(r.method for r in rows if r.scene == scene)))
        if grid is not None:
            figs.append(grid)
    md += "\n## Figures\n\n" + "\n".join(f"![{p.stem}]({p.relative_to(dest).as_posix()})" for p in figs) + "\n"
    atomic_write_text(md_path, md)
