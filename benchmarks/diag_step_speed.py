"""A splat training step's time: this checkout against a base commit, each in its own process, alternating.

The base commit is checked out into a temporary git worktree (`_common.base_worktree`, sharing this checkout's
`.venv`; its C++ kernels are built from its own sources). For each round folder given (`point_cloud.ply` and
`sparse/0`, e.g. the demo's or the real-size run's `round1`), a child process per version loads the trained
Gaussians and cameras and times training steps as `splat.train` takes them: the pose correction, the render
with SH degree 3, the L1 + SSIM loss, the backward and the fused Adam step, on one torch thread and the
compositor's `--threads`. The versions alternate process by process, `--rounds` times (use an even number: the
one that goes first alternates too), so both see the same machine load; the table gives each run and the ratio
of the means. The step's inputs are the same in both (a fixed random target), so only the code differs. A
diagnostic, not part of `make bench`.

Usage: .venv/bin/python benchmarks/diag_step_speed.py --base REF --run ROUND_DIR [--run ROUND_DIR ...]
           [--rounds N] [--steps S] [--threads T] [--page NAME]   (writes docs/bench/NAME.md, default step_speed)
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, base_worktree, cpu_model, md_table, write_fragment  # noqa: E402

# Run in the child, with the checkout under test first on sys.path.
_CHILD = r'''
import sys, time
root, run, steps, threads = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
sys.path.insert(0, root)
import torch
from pathlib import Path
from mvgeo.sparse_model import read_sparse_model
from mvgeo.transforms_torch import se3_exp
from splat.cameras_torch import homogeneous, pinhole_K
from splat.losses import photometric_loss
from splat.ply import read_gaussian_ply
from splat.rasterize import RasterConfig

torch.set_num_threads(1)
model = read_gaussian_ply(Path(run) / "point_cloud.ply")
sparse = read_sparse_model(Path(run) / "sparse" / "0")
views = [(torch.as_tensor(sparse.image(n).cam_from_world, dtype=torch.float32), pinhole_K(sparse.camera_of(n)))
         for n in sparse.names]
cam0 = sparse.camera_of(sparse.names[0])
W, H = cam0.width, cam0.height
params = list(model.parameters())
for p in params:
    p.requires_grad_(True)
opt = torch.optim.Adam([{"params": [p], "lr": 1e-4} for p in params], eps=1e-15, fused=True)
deltas = torch.zeros(len(views), 6, requires_grad=True)
raster = RasterConfig(num_threads=threads)
target = torch.rand(3, H, W, generator=torch.Generator().manual_seed(0))
bg = torch.zeros(3)

def step(i):
    cam_from_world, K = views[i % len(views)]
    out = model.render(se3_exp(deltas[i % len(views)]) @ homogeneous(cam_from_world), K, W, H, sh_degree=3,
                       background=bg, config=raster)
    loss = photometric_loss(out.rgb, target, ssim_weight=0.2, num_threads=threads)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()

for i in range(len(views)):  # warm-up: one pass over the views
    step(i)
t0 = time.perf_counter()
for i in range(steps):
    step(i)
print(f"RESULT {model.num_gaussians} {W} {H} {1e3 * (time.perf_counter() - t0) / steps:.3f}")
'''


def _git(*args: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def _time_steps(checkout: Path, run: Path, steps: int, threads: int) -> tuple[str, float]:
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE", DGS_NO_PROGRESS="1")
    proc = subprocess.run([str(ROOT / ".venv" / "bin" / "python"), "-c", _CHILD, str(checkout), str(run.resolve()),
                           str(steps), str(threads)], cwd=checkout, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"the step timing failed in {checkout} on {run}:\n{proc.stderr[-3000:]}")
    line = next(x for x in proc.stdout.splitlines() if x.startswith("RESULT "))
    n, w, h, ms = line.split()[1:]
    return f"{n} Gaussians, {w}x{h}", float(ms)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True, help="the commit to compare with")
    ap.add_argument("--run", type=Path, action="append", required=True,
                    help="a round folder with point_cloud.ply and sparse/0 (repeatable)")
    ap.add_argument("--rounds", type=int, default=4, help="processes per version and folder (default %(default)s)")
    ap.add_argument("--steps", type=int, default=34, help="timed steps per process, after one warm-up pass over "
                    "the views (default %(default)s)")
    ap.add_argument("--threads", type=int, default=2, help="compositor threads (the trainer's: the cores)")
    ap.add_argument("--page", default="step_speed", help="docs/bench/NAME.md to write")
    args = ap.parse_args()
    if args.rounds < 1 or args.steps < 1:
        ap.error("--rounds and --steps must be at least 1")
    for run in args.run:
        if not (run / "point_cloud.ply").is_file() or not (run / "sparse" / "0").is_dir():
            ap.error(f"{run}: not a round folder (point_cloud.ply and sparse/0 expected)")
    head = _git("rev-parse", "--short", "HEAD")
    dirty = _git("status", "--porcelain", "splat", "mvgeo")
    this = f"{head}{' + changes' if dirty else ''}"
    base = _git("rev-parse", "--short", args.base)
    load0 = " / ".join(f"{x:.1f}" for x in os.getloadavg())
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    times: dict[tuple[Path, str], list[float]] = {}
    labels: dict[Path, str] = {}
    with base_worktree(base, prefix="step_speed_") as wt:
        (wt / ".venv").symlink_to(ROOT / ".venv")
        for rnd in range(args.rounds):
            for run in args.run:
                # Which version runs first alternates from round to round: with the same code on both sides,
                # the second process of a pair measured 2-12 % slower, an order effect that this cancels.
                pair = (("base", wt), ("this", ROOT))
                for name, checkout in pair if rnd % 2 == 0 else pair[::-1]:
                    label, ms = _time_steps(checkout, run, args.steps, args.threads)
                    labels[run] = label
                    times.setdefault((run, name), []).append(ms)
                    print(f"round {rnd + 1}: {label}: {name} {ms:.1f} ms/step", file=sys.stderr, flush=True)
    load1 = " / ".join(f"{x:.1f}" for x in os.getloadavg())
    rows = []
    for run in args.run:
        b, t = times[(run, "base")], times[(run, "this")]
        mb, mt = sum(b) / len(b), sum(t) / len(t)
        rows.append([labels[run], " / ".join(f"{x:.1f}" for x in b), " / ".join(f"{x:.1f}" for x in t),
                     f"{mb:.1f}", f"{mt:.1f}", f"**{mt / mb:.2f}x**"])
    cmd = "OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/diag_step_speed.py " + " ".join(sys.argv[1:])
    body = (f"Base `{base}` against this checkout (`{this}`). {cpu_model()}, {os.cpu_count()} cores; {started}; "
            f"load average (1 / 5 / 15 min) {load0} before, {load1} after. Each cell: one process's mean over "
            f"{args.steps} training steps after a warm-up pass over the views (render with SH degree 3, L1 + SSIM "
            f"loss, backward, fused Adam; one torch thread, {args.threads} compositor threads); the versions "
            "alternate process by process, and the one that goes first alternates from round to round.\n\n")
    body += md_table(["Gaussians, size", "base (ms/step), each process", "this (ms/step), each process",
                      "base mean", "this mean", "this / base"], rows)
    path = write_fragment(args.page, "A training step: this checkout against a base commit", body,
                          reproduce=f"`{cmd}`")
    print(path)


if __name__ == "__main__":
    main()
