"""`denoise-gs eval --workers 2` against the serial path: wall time of a 4-task evaluation on this machine,
and the scores of both (they must be identical).

The sweep: `oracle_clean` (alignment + splat + held-out scoring) and `n2v_round1` (N2V training and
denoising first) with 2 seeds on `llff_like` at 128x96, 8 views: 4 independent runs (each method and
seed has its own folder, so the task graph has 4 chains of one).
Each command is its own process, as a user runs it: the serial one first, then the Ray one, in fresh
out folders, so both render the scene and run every stage (nothing from a cache). The Ray wall time
includes starting and stopping the local cluster.

The serial process runs torch with its default threads (the machine's cores), each Ray task with one;
the N2V training fixes its own count (`N2VConfig.torch_threads`), so the scores must be identical
(docs/cluster.md, "Threads and memory per task").

Run: `.venv/bin/python benchmarks/bench_ray.py` (writes docs/bench/ray.md; about 8 minutes on 2 cores).
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
from _common import ROOT, md_table, write_fragment  # noqa: E402

ARGS = ["eval", "llff_like", "--preset", "fast", "--size", "128x96", "--scene-views", "8", "--splat-iters", "300",
        "--seeds", "2", "--methods", "oracle_clean", "n2v_round1"]
SCORE_KEYS = ("scene", "method", "seed", "psnr_db", "ssim", "lpips", "rot_err_deg", "ate", "per_view", "error")
GOAL_RATIO = 0.8


def _cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def _run(out: Path, extra: list[str]) -> tuple[float, list[dict], float, float]:
    """(wall s, result rows, load average before, after) of one `denoise-gs eval` process."""
    env = {**os.environ, "DGS_NO_PROGRESS": "1", "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    cmd = [str(ROOT / ".venv" / "bin" / "denoise-gs"), *ARGS, "--out", str(out), *extra]
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
    with tempfile.TemporaryDirectory(prefix="bench_ray_") as tmp:
        serial_s, serial, l0, l1 = _run(Path(tmp) / "serial", [])
        # Peak RSS of the serial process: one run at a time, so about one task's memory (plus the driver's).
        serial_rss_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
        ray_s, ray, l2, l3 = _run(Path(tmp) / "ray", ["--workers", "2"])
    diff = _differences(ray, serial)
    ratio = ray_s / serial_s
    rows = [[f"{r['method']}, seed {r['seed']}", r["psnr_db"], s["psnr_db"], r["ssim"], s["ssim"], r["rot_err_deg"],
             s["rot_err_deg"]] for r, s in zip(ray, serial, strict=True)]
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    body = f"""Command (serial, then with `--workers 2`; fresh out folders):
`.venv/bin/denoise-gs {' '.join(ARGS)} --out OUT [--workers 2]`

Machine: {os.cpu_count()} cores ({_cpu_model()}), Python {platform.python_version()}; shared with other
engineers' jobs while measured: 1-minute load average {l0:.1f} -> {l1:.1f} during the serial run,
{l2:.1f} -> {l3:.1f} during the Ray run. Measured {now}. The serial process
runs torch with its default {threads} threads.

| path | wall (s) | ratio to serial | scores identical to serial |
|---|---|---|---|
| serial (`--workers 1`) | {serial_s:.1f} | 1 | |
| Ray, local cluster of 2 CPUs (`--workers 2`: 1 thread per run) | {ray_s:.1f} | **{ratio:.2f}x** | {_verdict(diff)} |

Goal: <= {GOAL_RATIO}x with `--workers 2`: {"met" if ratio <= GOAL_RATIO else "missed"}. The Ray times include
starting the cluster and its 2 worker processes (each imports torch and the project) and shutting it down.
"Identical" compares every field of every row but the measured seconds (per-view metrics included).

{md_table(["run", "PSNR Ray", "PSNR serial", "SSIM Ray", "SSIM serial", "rot. err. Ray", "rot. err. serial"],
          rows)}
Peak RSS of the serial process (one run at a time: about one task's memory): {serial_rss_mb:.0f} MiB.
"""
    path = write_fragment("ray", "Evaluation on Ray: --workers 2 against the serial path", body)
    print(path.read_text())
    return 0 if not diff else 1


def _verdict(diff: dict[str, float]) -> str:
    if not diff:
        return "yes"
    return "no: largest differences " + ", ".join(f"{k} {v:.2g}" for k, v in sorted(diff.items()))


if __name__ == "__main__":
    raise SystemExit(main())
