"""Whole-pipeline time per preset, image size and view count, with held-out quality alongside.

Each configuration is one `denoise-gs eval llff_like --methods product --seeds 1` in its own process (the
preset's whole pipeline, as `denoise-gs run` runs it, then held-out pose fitting and scoring): `--preset P
--size WxH --scene-views V`. `--method M` times another evaluation method. `llff_like` holds out every 8th
view, so 14 scene views give 12 training views and 20 give 17. Reported per run: the pipeline's recorded
seconds (every stage of every round, from the run's report.json), the evaluation's wall time (pipeline +
held-out pose fitting + scoring), the seconds per stage, the splat trainer's sub-steps where the report records
them, held-out PSNR / SSIM / LPIPS, and the machine's load before and after.

Usage:
    .venv/bin/python benchmarks/bench_pipeline_speed.py [--configs=fast:256x192:12,default:504x378:17]
        [--method=product] [--out=runs/bench_pipeline_speed_product] [--summarise]

`--configs` defaults to every combination of the `fast` and `default` presets, 256x192 and 504x378, 12 and 17
training views (eight runs; hours on 2 cores). Output folders are kept, so an interrupted benchmark resumes
(each eval output is resumable); the fragment docs/bench/pipeline_speed.md lists the runs found under `--out`,
not only those of this invocation."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import cli_option, md_table, write_fragment  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SCENE = "llff_like"
TRAIN_TO_SCENE_VIEWS = {12: 14, 17: 20}  # test_every = 8 in data_synth/scenes/llff_like.toml
DEFAULT_CONFIGS = [f"{p}:{s}:{v}" for p in ("fast", "default") for s in ("256x192", "504x378") for v in (12, 17)]


def _load() -> str:
    return " / ".join(f"{x:.1f}" for x in os.getloadavg())


def run_one(spec: str, out_root: Path, method: str) -> Path:
    preset, size, views = spec.split(":")
    n_train = int(views)
    if n_train not in TRAIN_TO_SCENE_VIEWS:
        raise SystemExit(f"--configs: training views must be one of {sorted(TRAIN_TO_SCENE_VIEWS)}, got {views}")
    out = out_root / f"{preset}_{size}_{n_train}"
    cmd = [str(ROOT / ".venv/bin/denoise-gs"), "eval", SCENE, "--out", str(out), "--seeds", "1",
           "--methods", method, "--preset", preset, "--size", size,
           "--scene-views", str(TRAIN_TO_SCENE_VIEWS[n_train]), "--max-size", "0"]
    meta = {"spec": spec, "method": method, "command": " ".join(cmd[1:]), "load_before": _load()}
    start = time.perf_counter()
    env = dict(os.environ, DGS_NO_PROGRESS="1", OMP_WAIT_POLICY=os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    proc = subprocess.run(cmd, cwd=ROOT, env=env, check=False, capture_output=True, text=True)
    meta.update(wall_s=time.perf_counter() - start, load_after=_load(), returncode=proc.returncode,
                date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    if proc.returncode != 0:
        meta["stderr_tail"] = proc.stderr[-2000:]
    out.mkdir(parents=True, exist_ok=True)
    (out_root / f"{out.name}.bench.json").write_text(json.dumps(meta, indent=2) + "\n")
    return out


def summarise(out_root: Path) -> tuple[list[list[object]], str, list[str]]:
    """(table rows, per-run details, the configurations found) for every run under `out_root`."""
    rows: list[list[object]] = []
    details = ""
    specs: list[str] = []
    for meta_path in sorted(out_root.glob("*.bench.json")):
        meta = json.loads(meta_path.read_text())
        specs.append(meta["spec"])
        out = out_root / meta_path.name.removesuffix(".bench.json")
        preset, size, views = meta["spec"].split(":")
        if meta["returncode"] != 0:
            rows.append([preset, size, views, "failed", "", "", "", "", meta["load_before"]])
            continue
        results = json.loads((out / "results.json").read_text())
        run = next(r for r in results["runs"] if r["method"] == meta.get("method", "denoise_gs_fused"))
        report = json.loads(next((out / "runs").glob("*/seed0/*/report.json")).read_text())
        stages = report["seconds_per_stage_recorded"]
        pipeline_s = sum(stages.values())
        rows.append([preset, size, views, f"{pipeline_s / 60:.1f}", f"{meta['wall_s'] / 60:.1f}",
                     f"{run['psnr_db']:.2f}", f"{run['ssim']:.3f}", f"{run['lpips']:.3f}",
                     f"{meta['load_before']} -> {meta['load_after']}"])
        details += (f"\n**{preset}, {size}, {views} training views** ({meta['date']}; `denoise-gs "
                    f"{meta['command']}`)\n\n")
        stage_rows = [[k, f"{v:.1f}", f"{100 * v / pipeline_s:.0f}%"] for k, v in stages.items()]
        details += md_table(["stage", "s", "share"], stage_rows)
        substeps = _splat_substeps(out)
        if substeps:
            keys = sorted({k for t in substeps.values() for k in t})
            details += "\nSplat trainer sub-steps per splat-training stage (seconds):\n\n"
            details += md_table(["sub-step", *substeps], [[k, *(f"{t.get(k, 0.0):.1f}" for t in substeps.values())]
                                                        for k in keys])
    return rows, details, specs


def _splat_substeps(out: Path) -> dict[str, dict[str, float]]:
    """The trainer's `timings_s` per splat-training stage (`roundN/splat`, `roundN/fuse`) whose record holds them."""
    found: dict[str, dict[str, float]] = {}
    for rec_path in sorted(out.glob("runs/*/seed0/*/round*/stages/*.json")):
        try:
            rec = json.loads(rec_path.read_text())
        except (OSError, ValueError):
            continue
        timings = (rec.get("summary") or {}).get("timings_s") if isinstance(rec, dict) else None
        if isinstance(timings, dict) and timings:
            found[f"{rec_path.parent.parent.name}/{rec_path.stem}"] = {
                k: float(v) for k, v in timings.items() if isinstance(v, (int, float))}
    return found


def main(argv: list[str]) -> int:
    configs = cli_option("configs", ",".join(DEFAULT_CONFIGS)).split(",")
    method = cli_option("method", "product")
    out_root = Path(cli_option("out", str(ROOT / "runs" / f"bench_pipeline_speed_{method}")))
    out_root.mkdir(parents=True, exist_ok=True)
    if "--summarise" not in argv:
        for spec in configs:
            print(f"[{time.strftime('%H:%M:%S')}] {spec} (load {_load()})", flush=True)
            run_one(spec, out_root, method)
    rows, details, found = summarise(out_root)
    body = (
        "Reproduce: `.venv/bin/python benchmarks/bench_pipeline_speed.py --configs="
        f"{','.join(found)} --method={method}` (`make bench ONLY=pipeline_speed` runs all eight "
        "configurations; each run is its own process, one after the other; `--summarise` rebuilds this page "
        "from the runs kept under `--out`).\n\n"
        f"`denoise-gs eval {SCENE} --methods {method} --seeds 1` per configuration: the preset's pipeline "
        "as `denoise-gs run` runs it, then held-out pose fitting and scoring against the clean test views. "
        "`pipeline min`: the stages' recorded time (the user's wait for `denoise-gs run`); `eval min`: "
        "the whole evaluation. 2 shared CPU cores; the load column says how busy the machine was. "
        "Goal: `default` at 504x378 with 17 views in 15 minutes or less. Before/after figures for the "
        "changes that set these times, with their quality A/B runs: docs/bench/pipeline_schedule.md. "
        "The held-out scores compare presets and sizes at one view count; across view counts the scenes "
        "differ (`--scene-views` 14 or 20 spreads the cameras differently and holds out 2 or 3 views).\n\n"
        + md_table(["preset", "size", "training views", "pipeline min", "eval min", "PSNR", "SSIM", "LPIPS",
                    "load before -> after"], rows)
        + "\n### Per run\n" + details
    )
    path = write_fragment("pipeline_speed", "Whole-pipeline time per preset (pipeline_speed)", body)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
