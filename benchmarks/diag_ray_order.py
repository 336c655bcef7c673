"""The order an evaluation's runs start in on Ray: a base commit against this checkout, on one sweep.

`denoise-gs eval llff_like --preset fast --splat-iters 300 --size 128x96 --scene-views 8 --seeds 2 --methods
instantsplat n2v_round1` is the usual comparison, the noisy-photo baseline against a denoiser, in its smallest
form: per seed one short run ((b): alignment and splat) and one long one (the denoiser's training first). The
serial order is seeds, then methods (I0, N0, I1, N1). It runs once serially (this checkout; the serial path
does not depend on the order), then with `--workers 2` from the base commit's code (a temporary
`git worktree`) and from this checkout, alternating, `--repeats` times each, every command in a fresh out
folder and its own process with its working folder at the code it runs (the workers import the driver's
code). Prints the wall seconds and whether every score field of every row equals the serial run's.

`--sweep gt`: the ground-truth-pose variants instead (`eval.evaluate.task_graph`), `--seeds 1 --methods
instantsplat oracle_clean instantsplat@gt_poses oracle_clean@gt_poses` on the same scene: two runs, then two
variants that each read their method's run and oracle_clean's points. `--sweep gt_n2v` adds `n2v_round1` and
its variant (the denoiser's training is then the longest chain).

Run: `.venv/bin/python benchmarks/diag_ray_order.py BASE [--repeats 2] [--sweep order|gt|gt_n2v]` (about 8 minutes on
2 cores for `order`).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, base_worktree  # noqa: E402

SCENE = ["eval", "llff_like", "--preset", "fast", "--splat-iters", "300", "--size", "128x96", "--scene-views", "8"]
SWEEPS = {"order": [*SCENE, "--seeds", "2", "--methods", "instantsplat", "n2v_round1"],
          "gt": [*SCENE, "--seeds", "1", "--methods", "instantsplat", "oracle_clean", "instantsplat@gt_poses",
                 "oracle_clean@gt_poses"],
          "gt_n2v": [*SCENE, "--seeds", "1", "--methods", "instantsplat", "n2v_round1", "oracle_clean",
                     "instantsplat@gt_poses", "n2v_round1@gt_poses", "oracle_clean@gt_poses"]}
SCORES = ("method", "seed", "psnr_db", "ssim", "lpips", "rot_err_deg", "ate", "per_view", "error")


def _eval(tree: Path, out: Path, sweep: list[str], extra: list[str]) -> tuple[float, list[dict]]:
    """(wall seconds, score fields of the rows) of one `denoise-gs eval` with `tree`'s code."""
    env = {**os.environ, "DGS_NO_PROGRESS": "1", "OMP_WAIT_POLICY": "PASSIVE", "PYTHONPATH": str(tree)}
    code = "import sys; from eval.cli import main; sys.exit(main(sys.argv[1:]))"
    start = time.perf_counter()
    run = subprocess.run([sys.executable, "-c", code, *sweep, "--out", str(out), *extra], cwd=tree, env=env,
                         capture_output=True, text=True)
    wall = time.perf_counter() - start
    if run.returncode != 0:
        raise SystemExit(f"eval with {tree} exited {run.returncode}: {run.stderr[-2000:]}")
    rows = json.loads((out / "results.json").read_text())["runs"]
    return wall, [{k: r.get(k) for k in SCORES} for r in rows]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("base", help="the commit to compare with (e.g. the one before the change)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--sweep", choices=sorted(SWEEPS), default="order")
    args = ap.parse_args()
    sweep = SWEEPS[args.sweep]
    print(" ".join(["denoise-gs", *sweep]), flush=True)
    with base_worktree(args.base, prefix="ray_order_") as base_tree:
        work = base_tree.parent
        serial_s, serial_rows = _eval(ROOT, work / "serial", sweep, [])
        print(f"serial (this checkout): {serial_s:.1f} s, load {os.getloadavg()[0]:.1f}", flush=True)
        walls: dict[str, list[float]] = {"base": [], "this": []}
        for k in range(args.repeats):
            for who, tree in (("base", base_tree), ("this", ROOT)):
                s, rows = _eval(tree, work / f"{who}{k}", sweep, ["--workers", "2"])
                walls[who].append(s)
                print(f"--workers 2, {who}: {s:.1f} s ({s / serial_s:.2f}x the serial), scores "
                      f"{'identical' if rows == serial_rows else 'DIFFERENT'}, load {os.getloadavg()[0]:.1f}",
                      flush=True)
        for who in walls:
            print(f"{who}: {' / '.join(f'{s:.1f}' for s in walls[who])} s; "
                  f"{' / '.join(f'{s / serial_s:.2f}x' for s in walls[who])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
