"""`denoise-gs eval --workers 2` against the serial path: wall time of two 4-task evaluations on this machine,
and the scores of both paths (they must be identical).

The sweeps, on `llff_like`, each 4 independent runs (every method and seed has its own folder, so the task
graph has 4 chains of one):
- `oracle`: `oracle_clean` (alignment + splat + held-out scoring) with 4 seeds at 256x192, 12 views (the
  demo's size: runs of about a minute, so the time ratio is the runs', not the cluster's start-up);
- `n2v`: `oracle_clean` and `n2v_round1` (N2V training and denoising first) with 2 seeds at 128x96, 8 views:
  the scores check with the denoiser in the runs;
- `n2v_256`: `n2v_round1` with 4 seeds at the `oracle` sweep's size: every run trains a denoiser, at a size
  where the runs, not the cluster's start-up, set the time.
Each command is its own process, as a user runs it: the serial one first, then the Ray one, in fresh
out folders, so both render the scene and run every stage (nothing from a cache). The Ray wall time
includes starting and stopping the local cluster.

The serial process runs torch with its default threads (the machine's cores), each Ray task with one;
the denoiser runs one torch thread per piece of work (`denoise.parallel`) and the scoring fixes its
count (`eval.image_metrics.SCORING_THREADS`), so the scores must be identical (docs/cluster.md, "Threads and
memory per task").

Run: `.venv/bin/python benchmarks/bench_ray.py` (writes docs/bench/ray.md; about 20 minutes on 2 cores).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, cpu_model, md_table, write_fragment  # noqa: E402

ARGS = ["eval", "llff_like", "--preset", "fast", "--splat-iters", "300"]
SWEEPS = {"oracle": ["--size", "256x192", "--scene-views", "12", "--seeds", "4", "--methods", "oracle_clean"],
          "n2v": ["--size", "128x96", "--scene-views", "8", "--seeds", "2", "--methods", "oracle_clean", "n2v_round1"],
          "n2v_256": ["--size", "256x192", "--scene-views", "12", "--seeds", "4", "--methods", "n2v_round1"]}
SCORE_KEYS = ("scene", "method", "seed", "psnr_db", "ssim", "lpips", "rot_err_deg", "ate", "per_view", "error")
GOAL_RATIO = 0.8


def _run(out: Path, sweep: list[str], extra: list[str]) -> tuple[float, list[dict], float, float]:
    """(wall s, result rows, load average before, after) of one `denoise-gs eval` process."""
    env = {**os.environ, "DGS_NO_PROGRESS": "1", "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    cmd = [str(ROOT / ".venv" / "bin" / "denoise-gs"), *ARGS, *sweep, "--out", str(out), *extra]
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    load_after = os.getloadavg()[0]
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr[-4000:])
        raise SystemExit(f"{' '.join(cmd)} exited {proc.returncode}")
    rows = json.loads((out / "results.json").read_text())["runs"]
    return wall, rows, load_before, load_after


def _leaves(x: object, path: str = "") -> dict[str, object]:
    """Flattened JSON: path -> value."""
    if isinstance(x, dict):
        return {k: v for key, val in x.items() for k, v in _leaves(val, f"{path}/{key}").items()}
    if isinstance(x, list):
        return {k: v for i, val in enumerate(x) for k, v in _leaves(val, f"{path}[{i}]").items()}
    return {path: x}


def _differences(a: list[dict], b: list[dict]) -> dict[str, float]:
    """Score field (per-view fields by metric) -> largest absolute difference between the two runs' rows."""
    out: dict[str, float] = {}
    for ra, rb in zip(a, b, strict=True):
        la, lb = _leaves({k: ra[k] for k in SCORE_KEYS}), _leaves({k: rb[k] for k in SCORE_KEYS})
        for key in sorted(set(la) | set(lb)):
            va, vb = la.get(key), lb.get(key)
            if va == vb:
                continue
            field = key.rsplit("/", 1)[-1] if key.startswith("/per_view") else key.strip("/")
            gap = abs(va - vb) if isinstance(va, float) and isinstance(vb, float) else float("inf")
            out[field] = max(out.get(field, 0.0), gap)
    return out


def main() -> int:
    import torch

    threads = torch.get_num_threads()
    results, loads, rss = {}, [], 0.0
    with tempfile.TemporaryDirectory(prefix="bench_ray_") as tmp:
        for name, sweep in SWEEPS.items():
            serial_s, serial, l0, l1 = _run(Path(tmp) / name / "serial", sweep, [])
            # Peak RSS of a serial process: one run at a time, so about one task's memory (plus the driver's).
            rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
            ray_s, ray, l2, l3 = _run(Path(tmp) / name / "ray", sweep, ["--workers", "2"])
            results[name] = (serial_s, serial, ray_s, ray)
            loads.append(f"{name}: {l0:.1f} -> {l1:.1f} serial, {l2:.1f} -> {l3:.1f} Ray")
    table, scores, failed = [], [], False
    for name, (serial_s, serial, ray_s, ray) in results.items():
        diff = _differences(ray, serial)
        failed |= bool(diff)
        ratio = ray_s / serial_s
        table.append([f"`{name}`: {' '.join(SWEEPS[name])}", f"{serial_s:.1f}", f"{ray_s:.1f}", f"**{ratio:.2f}x**",
                      "met" if ratio <= GOAL_RATIO else "missed", f"{ray_s - serial_s / 2:.1f}", _verdict(diff)])
        scores += [_score_row(name, r, s) for r, s in zip(ray, serial, strict=True)]
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    body = f"""Command (serial, then with `--workers 2`; fresh out folders):
`.venv/bin/denoise-gs {' '.join(ARGS)} SWEEP --out OUT [--workers 2]`

Machine: {os.cpu_count()} cores ({cpu_model()}), Python {platform.python_version()}; 1-minute load average
({'; '.join(loads)}). Measured {now}. The serial process runs torch with its default {threads} threads, each
Ray task with one (the denoiser one per piece of work, on as many Python threads as the run has
torch threads; the scoring with 1).

{md_table(["sweep (4 runs)", "serial (s)", "`--workers 2` (s)", "ratio", f"goal <= {GOAL_RATIO}x",
           "above half the serial (s)", "scores identical to serial"], table)}
The Ray times include starting the cluster and its 2 worker processes (each imports torch and the project)
and shutting it down; "above half the serial" is that cost plus the idle worker at the end (tasks of
unequal length) plus the slowdown of two runs sharing the machine's memory bandwidth.
"Identical" compares every field of every row but the measured seconds (per-view
metrics included). Where the serial run already keeps both cores busy (the denoiser's chunks and passes,
the compositor) a second worker has less to gain.

{md_table(["sweep", "run", "PSNR Ray", "PSNR serial", "LPIPS Ray", "LPIPS serial", "rot. err. Ray",
           "rot. err. serial"], scores)}
Peak RSS of a serial process (one run at a time: about one task's memory): {rss:.0f} MiB.
"""
    path = write_fragment("ray", "Evaluation on Ray: --workers 2 against the serial path", body)
    print(path.read_text())
    return 1 if failed else 0


def _score_row(name: str, ray: dict, serial: dict) -> list:
    """A row of the scores table; a failed run shows its error's type (both paths' errors are compared)."""
    if ray.get("error") or serial.get("error"):
        def kind(row: dict) -> str:
            return f"failed: {str(row['error']).split(':', 1)[0]}" if row.get("error") else "scored"
        return [name, f"{ray['method']}, seed {ray['seed']}", kind(ray), kind(serial), "", "", "", ""]
    return [name, f"{ray['method']}, seed {ray['seed']}", ray["psnr_db"], serial["psnr_db"], ray["lpips"],
            serial["lpips"], ray["rot_err_deg"], serial["rot_err_deg"]]


def _verdict(diff: dict[str, float]) -> str:
    if not diff:
        return "yes"
    return "no: largest differences " + ", ".join(f"{k} {v:.2g}" for k, v in sorted(diff.items()))


if __name__ == "__main__":
    raise SystemExit(main())
