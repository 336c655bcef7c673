"""Is the held-out pose fit converged? Score finished runs with several lengths of the test-time pose fit.

`denoise-gs eval` refines each held-out camera photometrically with the Gaussians frozen (`splat.pose_fit`,
200 Adam steps by default, the learning rate decaying from 2e-3 to 1e-5 over the steps) before it renders and
scores the view. If the fit were stopped short, every held-out score would carry the remaining pose error, and
the methods with the worse starting poses would lose most. This script rescores a finished run's round folder
(`point_cloud.ply`, `sparse/0`) with each length, exactly as `eval` scores it (`eval.evaluate.score_reconstruction`),
and writes the held-out means and the time per scoring.

Usage: .venv/bin/python benchmarks/diag_pose_fit_iters.py --iters=50,100,200,500 [--page=NAME]
       DATASET:ROUND_DIR [DATASET:ROUND_DIR ...]
(DATASET: the evaluation dataset; ROUND_DIR: e.g. `OUT/runs/SCENE/seed0/product/round1`; `--page` writes
docs/bench/NAME.md)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from _common import ROOT, cli_option, cpu_model, md_table, write_fragment

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads


def main() -> int:
    from eval.evaluate import score_reconstruction
    from eval.pipeline.validate import validate_dataset_folder

    iters = [int(x) for x in cli_option("iters", "50,100,200,500").split(",")]
    page = cli_option("page", "")
    runs = [a for a in sys.argv[1:] if not a.startswith("--")]
    if not runs or any(":" not in r for r in runs):
        print("usage: diag_pose_fit_iters.py --iters=50,100,200,500 [--page=NAME] DATASET:ROUND_DIR ...",
              file=sys.stderr)
        return 2
    rows = []
    for spec in runs:
        data, run = spec.split(":", 1)
        dataset = validate_dataset_folder(Path(data))
        for n in iters:
            t = time.perf_counter()
            s = score_reconstruction(Path(run), dataset, pose_fit_iters=n)
            sec = time.perf_counter() - t
            row = [run, n, f"{s['psnr_db']:.3f}", f"{s['ssim']:.4f}", f"{s['lpips']:.4f}", f"{sec:.0f}"]
            print(row, flush=True)
            rows.append(row)
    table = md_table(["round folder", "pose-fit steps", "PSNR (dB)", "SSIM", "LPIPS", "scoring (s)"], rows)
    print(table)
    if page:
        cmd = " ".join(["`.venv/bin/python benchmarks/diag_pose_fit_iters.py", *sys.argv[1:]]) + "`"
        body = (f"Machine: {cpu_model()}, 2 cores; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Held-out "
                f"means as `denoise-gs eval` scores them; seconds for the whole scoring of the run (its held-out "
                f"views' pose fits, renders and metrics).\n\n{table}")
        write_fragment(page, "Held-out pose fitting: scores by the length of the fit", body, reproduce=cmd)
        print(ROOT / "docs" / "bench" / f"{page}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
