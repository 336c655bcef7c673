"""Each held-out view's score of finished runs, with the current held-out pose fit.

`denoise-gs eval` maps each held-out camera from the ground truth into the run's frame (a Sim(3) on the
training cameras, `eval.heldout`), refines it photometrically with the Gaussians frozen (`splat.pose_fit`)
and scores the render against the clean photo. This rescores finished round folders that way and prints the
mean and every view's PSNR, so that one view whose fit went wrong shows (`results.json` holds the
evaluation's own per-view scores, from the fit as it was then).

Usage: .venv/bin/python benchmarks/diag_heldout_views.py [--iters=N,N,...] DATASET ROUND_DIR [ROUND_DIR ...]
(DATASET: the evaluation dataset; ROUND_DIR: e.g. `OUT/runs/SCENE/seed0/product/round1`; `--iters`: the
lengths of the pose fit, one row each, 0 = the mapped camera unfitted; default: the evaluation's)
"""
import sys
from pathlib import Path

import numpy as np
from _common import cli_option

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads


def main() -> int:
    from eval.evaluate import EvalConfig, _score_scene, _stem_poses
    from eval.pipeline.validate import validate_dataset_folder
    from mvgeo.sparse_model import read_sparse_model
    from splat.ply import read_gaussian_ply

    iters_text = cli_option("iters", "")
    lengths = [int(x) for x in iters_text.split(",")] if iters_text else [None]
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if len(args) < 2:
        print(__doc__.strip().splitlines()[-3], file=sys.stderr)
        return 2
    ds = validate_dataset_folder(Path(args[0]))
    gt = read_sparse_model(ds.root / "sparse" / "0")
    print("| round folder | pose-fit steps | PSNR / SSIM / LPIPS | per view (PSNR) |")
    print("|---|---|---|---|")
    for run in args[1:]:
        rd = Path(run)
        est = read_sparse_model(rd / "sparse" / "0")
        model = read_gaussian_ply(rd / "point_cloud.ply", device="cpu")
        for n in lengths:
            per_view, _ = _score_scene(model, gt, _stem_poses(est), ds, EvalConfig(pose_fit_iters=n),
                                       [est.camera_of(c) for c in est.names])
            m = {k: float(np.mean([v[k] for v in per_view.values()])) for k in ("psnr_db", "ssim", "lpips")}
            views = ", ".join(f"{k} {v['psnr_db']:.2f}" for k, v in per_view.items())
            print(f"| {run} | {'default' if n is None else n} | {m['psnr_db']:.2f} / {m['ssim']:.3f} / "
                  f"{m['lpips']:.3f} | {views} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
