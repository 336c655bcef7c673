"""The `@gt_poses` variant of methods an evaluation already ran, without running the methods again.

`denoise-gs eval --gt-pose-variants` runs each method and then its variant; when the methods' runs exist
but their stage keys no longer match the code (an edit since), this script takes each method's finished
round folder as it is and runs only the variant's two stages (`eval.baselines.gt_align`: `oracle_clean`'s
alignment points on the true cameras' rays; the pipeline's splat stage with the known-pose preset) into
`EVAL_OUT/runs/SCENE/seed0/<folder>@gt_poses`, then scores it as `denoise-gs eval` does (true held-out poses,
clean images). Prints one row per method.

Usage: .venv/bin/python benchmarks/diag_gt_pose_variant.py EVAL_OUT DATASET --splat-iters N METHOD...
(METHOD: an `eval.methods.METHODS` name, e.g. instantsplat n2v_round1 n2v_fused_round1 oracle_clean; DATASET:
the dataset folder the evaluation scored against, at its working size: EVAL_OUT/data/<name>_max512 when the
evaluation downscaled it)."""
import argparse
import dataclasses
import sys
from pathlib import Path

from _common import held_out_at_true_poses

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from eval.methods import METHODS, ORACLE_CLEAN, _splat_on_ground_truth, gt_pose_variant, splat_photos
from eval.pipeline import preset
from eval.pipeline.validate import validate_dataset_folder

ap = argparse.ArgumentParser()
ap.add_argument("eval_out", type=Path)
ap.add_argument("dataset", type=Path)
ap.add_argument("methods", nargs="+")
ap.add_argument("--splat-iters", type=int, required=True)
ap.add_argument("--seed", type=int, default=0)
args = ap.parse_args()
dataset = validate_dataset_folder(args.dataset)
scene = next(p.name for p in (args.eval_out / "runs").iterdir())
seed_dir = args.eval_out / "runs" / scene / f"seed{args.seed}"
base = preset("default", views=min(12, len(dataset.train)))
base = dataclasses.replace(base, max_size=None, seed=args.seed,
                           splat=dataclasses.replace(base.splat, iters=args.splat_iters))
print("| method | PSNR | SSIM | LPIPS |\n|---|---|---|---|", flush=True)
for name in args.methods:
    own = METHODS[name]
    variant = gt_pose_variant(own, ORACLE_CLEAN)
    round_dir = seed_dir / own.folder() / "round1"
    points_dir = seed_dir / ORACLE_CLEAN.folder() / "round1"  # every variant starts from the clean photos' points
    photos = splat_photos(round_dir, own.pipeline_config(base).fuse_noisy_splat)
    rec = _splat_on_ground_truth(variant.stages(dataset), variant.pipeline_config(base), dataset,
                                 photos, seed_dir / variant.folder(), estimate=points_dir)
    m = held_out_at_true_poses(rec.round_dir, dataset)
    print(f"| {variant.name} | {m['psnr_db']:.2f} | {m['ssim']:.3f} | {m['lpips']:.3f} |", flush=True)
sys.exit(0)
