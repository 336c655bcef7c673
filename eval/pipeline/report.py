"""`OUT/report.json` and `OUT/report.md` (with contact sheets) of a pipeline run.

The report is committed like a stage's outputs (`eval.pipeline.stage.commit_written`): written in a
hidden work folder, then moved into place, with a record `OUT/stages/report.json` of every file, so
that a later run replaces or withdraws only files it wrote (`REPORT_OUTPUTS`)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from eval.contact_sheet import contact_sheet
from eval.pipeline.config import PipelineConfig
from eval.pipeline.quality import quality_lines, round_camera_plot, round_quality
from eval.pipeline.rounds import RoundResult, StoppedRound
from eval.pipeline.stage import StageResult, commit_written
from eval.pipeline.summaries import ExportSummary, InputsSummary, SelectSummary, WorkingSize
from eval.pipeline.views import view_files
from mvgeo.common.atomic import atomic_write_text
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, write_image

__all__ = ["CONTACT_ROWS", "REPORT_OUTPUTS", "REPORT_RECORD", "write_report"]

#: Views shown per contact sheet (evenly spaced over the round's views).
CONTACT_ROWS = 6
#: What the report writes in OUT, and the name of its record (`OUT/stages/<name>.json`).
REPORT_OUTPUTS = ("report.json", "report.md", "report_files")
REPORT_RECORD = "report"


def _json_safe(x: object) -> object:
    """Replace non-finite floats (not valid JSON) by strings."""
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_safe(v) for v in x]
    return x


def _images(folder: Path) -> dict[str, Path]:
    try:
        return view_files(folder)
    except InputError:
        return {}


def _contact_sheet_png(dest: Path, images_dir: Path, rd: Path, r: int) -> Path | None:
    """Write `dest/report_files/contact_round<r>.png` (None when the round has no denoised images)."""
    denoised = _images(rd / "denoised")
    if not denoised:
        return None
    noisy, renders = _images(images_dir), _images(rd / "renders")
    names = list(denoised)
    idx = np.unique(np.linspace(0, len(names) - 1, min(CONTACT_ROWS, len(names))).round().astype(int))
    shown = [names[i] for i in idx]
    rows = [[read_image(noisy[n]) if n in noisy else None, read_image(denoised[n]),
             read_image(renders[n]) if n in renders else None] for n in shown]
    sheet = contact_sheet(rows, titles=["noisy", f"denoised (round {r})", f"render (round {r})"],
                          row_labels=shown)
    path = dest / "report_files" / f"contact_round{r}.png"
    write_image(path, sheet)
    return path


def _size_lines(config: PipelineConfig, sizes: Mapping[str, WorkingSize]) -> list[str]:
    """The report's line on the working resolution: `WxH (from W0xH0)` per distinct pair."""
    if not sizes:
        return []
    pairs = sorted({(v.working_wh, v.input_wh) for v in sizes.values()})
    shown = ", ".join(f"{w[0]}x{w[1]}" + (f" (from {i[0]}x{i[1]})" if i != w else " (input size)")
                      for w, i in pairs)
    limit = "none (input size)" if config.max_size is None else f"long side <= {config.max_size} px"
    lines = [f"- working size: {shown}; --max-size: {limit}"]
    turned = sorted(k for k, v in sizes.items() if v.turned)
    if turned:
        lines.append(f"- turned a quarter counter-clockwise to the others' orientation (portrait among landscape, "
                     f"or the reverse): {', '.join(turned)}; their working images, denoised photos and renders "
                     "stay turned, their cameras in `cameras/input/` are turned back")
    if config.align.intrinsics is not None:
        lines.append(f"- calibration: `{config.align.intrinsics}` (given with --intrinsics; the alignment used it, "
                     "scaled to the working size, instead of estimating the focal length)")
    return lines


def write_report(out: Path, *, images_dir: Path, config: PipelineConfig, rounds: Sequence[RoundResult],
                 timings_s: dict[str, float], working: StageResult | None = None,
                 exported: StageResult | None = None, stopped: StoppedRound | None = None) -> tuple[Path, Path]:
    """Write `report.json`, `report.md` and `report_files/contact_round<N>.png` (module docstring).

    Args:
        out: the run's output folder.
        images_dir: the noisy inputs (first column of the contact sheets).
        config: the run's settings.
        rounds: per-round stage results.
        timings_s: this invocation's seconds per stage (skipped stages absent) and `total`.
        working: the `inputs` stage (working images and their sizes), if it ran.
        exported: the `export` stage (scene.splat, view/, cameras/), if it ran.
        stopped: the round the loop stopped in after its refine, if any (its stages are listed too).

    Returns:
        (report.json, report.md) paths.

    Raises:
        UnownedOutputError: the previous report's files hold files the run did not write or that changed
            (`eval.pipeline.stage.UnownedOutputError`; nothing is replaced).
    """
    commit_written(out, REPORT_RECORD, REPORT_OUTPUTS, lambda work: _write_report_files(
        out, work, images_dir=images_dir, config=config, rounds=rounds, timings_s=timings_s, working=working,
        exported=exported, stopped=stopped))
    return out / "report.json", out / "report.md"


def _write_report_files(out: Path, dest: Path, *, images_dir: Path, config: PipelineConfig,
                        rounds: Sequence[RoundResult], timings_s: dict[str, float], working: StageResult | None,
                        exported: StageResult | None, stopped: StoppedRound | None) -> None:
    """The report of the run in `out`, written into `dest` (`write_report`'s arguments)."""
    stages = []
    selected: dict[str, list[str]] = {}
    for rnd in [*rounds, *([stopped] if stopped is not None else [])]:
        for name, res in rnd.stages.items():
            stages.append({"round": rnd.index, "stage": name, "key": res.key, "skipped": res.skipped,
                           "seconds": round(res.seconds, 4), "summary": res.summary})
            if name == "select":
                selected[f"round{rnd.index}"] = list(SelectSummary.from_json(res.summary).selected)
    noisy_dir = out / "inputs" if working is not None else images_dir  # same size as the renders
    sheets = {rnd.index: _contact_sheet_png(dest, noisy_dir, rnd.dir, rnd.index) for rnd in rounds}
    sizes = InputsSummary.from_json(working.summary).sizes if working is not None else {}
    export = ExportSummary.from_json(exported.summary) if exported is not None else None
    quality = [round_quality(rnd) for rnd in rounds]
    camera_plots = {rnd.index: round_camera_plot(dest, rnd) for rnd in rounds}
    report = {
        "images_dir": str(images_dir),
        "settings": config.to_dict(),
        "timings_s_this_run": timings_s,
        "seconds_per_stage_recorded": {f"round{s['round']}/{s['stage']}": s["seconds"] for s in stages},
        "stages": stages,
        "selected_views": selected,
        "rounds": [{"index": rnd.index, "dir": rnd.dir.name} for rnd in rounds],
        "result_round": rounds[-1].index if rounds else None,
        "stopped": None if stopped is None else {"round": stopped.index, "reason": stopped.reason},
        "contact_sheets": {f"round{k}": str(v.relative_to(dest)) for k, v in sheets.items() if v is not None},
        "max_size": config.max_size,
        "image_sizes": {k: v.to_json() for k, v in sizes.items()},
        "export": export.to_json() if export is not None else None,
        "quality": {f"round{q.index}": q.to_json() for q in quality},
        "camera_plots": {f"round{k}": str(v.relative_to(dest)) for k, v in camera_plots.items() if v is not None},
    }
    json_path, md_path = dest / "report.json", dest / "report.md"
    atomic_write_text(json_path, json.dumps(_json_safe(report), indent=2) + "\n")

    lines = ["# Denoise-GS run", "", f"- inputs: `{images_dir}`",
             f"- rounds: {config.rounds}, views kept for rounds >= 2: {config.views}, seed: {config.seed}, "
             f"device: {config.device}"]
    if stopped is not None:
        lines.append(f"- **{stopped.reason}**")
    lines += _size_lines(config, sizes)
    if export is not None:
        lines += ["- scene: [`scene.splat`](scene.splat) (antimatter15 .splat, "
                  f"{'?' if export.num_gaussians is None else export.num_gaussians} Gaussians) and an offline viewer "
                  "[`view/index.html`](view/index.html) (opens from disk, no network); cameras: "
                  "`cameras/working/` (working size), `cameras/input/` (intrinsics scaled to the input photos)"]
    lines.append("")
    lines += ["## Stages", "", "| round | stage | status | seconds | key |", "|---|---|---|---|---|"]
    for s in stages:
        status = "skipped (complete)" if s["skipped"] else "ran"
        lines.append(f"| {s['round']} | {s['stage']} | {status} | {s['seconds']:.2f} | `{s['key'][:12]}` |")
    total = sum(s["seconds"] for s in stages)
    lines += ["", f"Recorded stage time, all rounds: {total:.1f} s (this invocation: "
              f"{timings_s.get('total', 0.0):.1f} s; skipped stages cost nothing).", ""]
    if any(q.denoise or q.align or q.splat for q in quality):
        lines += quality_lines(quality)
    if any(camera_plots.values()):
        lines += ["## Cameras", ""]
        for k, v in camera_plots.items():
            if v is not None:
                lines += [f"![round {k} cameras]({v.relative_to(dest).as_posix()})", ""]
    if selected:
        lines += ["## Selected views", ""]
        lines += [f"- {k}: {', '.join(v)}" for k, v in selected.items()]
        lines.append("")
    if any(sheets.values()):
        lines += ["## Contact sheets (noisy | denoised | render)", ""]
        for k, v in sheets.items():
            if v is not None:
                lines += [f"### Round {k}", "", f"![round {k}]({v.relative_to(dest).as_posix()})", ""]
    lines += ["## Settings", "", "```json", json.dumps(config.to_dict(), indent=2), "```", ""]
    atomic_write_text(md_path, "\n".join(lines))
