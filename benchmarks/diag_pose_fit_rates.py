"""Each held-out view's score with the held-out pose fit at each learning-rate scale, and with the scales combined.

`denoise-gs eval` refines each held-out camera photometrically against the noisy held-out photo with the Gaussians
frozen (`splat.pose_fit.fit_pose`). This rescores finished round folders with one fit per scale of the fit's
learning rate (`PoseFitConfig.lr_scales`), and with the fits combined as `fit_pose` combines them (the pose
of lowest loss against the noisy photo: no ground truth in the choice). The PSNR is against the clean photo.

Usage: .venv/bin/python benchmarks/diag_pose_fit_rates.py [--scales=1,0.25] DATASET:ROUND_DIR ...
(DATASET: the evaluation dataset; ROUND_DIR: e.g. `OUT/runs/SCENE/seed0/product/round1`, a run with its own
cameras). Prints a Markdown table: PSNR (dB) per view, and each run's means.
"""
import sys
import time
from pathlib import Path

import numpy as np
from _common import cli_option, cpu_model

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads


def main() -> int:
    import torch

    from eval.evaluate import _stem_poses, heldout_camera
    from eval.heldout import map_cameras_local
    from eval.image_metrics import score_images
    from eval.pipeline.validate import validate_dataset_folder
    from mvgeo.common.imageio import read_image
    from mvgeo.sparse_model import read_sparse_model
    from splat.losses import photometric_loss
    from splat.ply import read_gaussian_ply
    from splat.pose_fit import PoseFitConfig, fit_pose
    from splat.render import render_views

    scales = [float(x) for x in cli_option("scales", "1,0.25").split(",")]
    pairs = [a.split(":", 1) for a in sys.argv[1:] if not a.startswith("--")]
    if not pairs or any(len(p) != 2 for p in pairs):
        print(__doc__.strip().splitlines()[-3], file=sys.stderr)
        return 2
    cols = [f"x{s:g}" for s in scales] + ["combined"]
    print(f"{cpu_model()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    lines = [f"| round folder | view | start | {' | '.join(cols)} |", "|---|---|---|" + "---|" * len(cols)]
    means = []
    for ds_path, run in pairs:
        ds = validate_dataset_folder(Path(ds_path))
        rd = Path(run)
        gt, est = read_sparse_model(ds.root / "sparse" / "0"), read_sparse_model(rd / "sparse" / "0")
        model = read_gaussian_ply(rd / "point_cloud.ply", device="cpu")
        gtp, estp = _stem_poses(gt), _stem_poses(est)
        starts = map_cameras_local(estp, {n: gtp[n] for n in ds.train}, {n: gtp[n] for n in ds.test}).cam_from_world
        est_cams = [est.camera_of(c) for c in est.names]
        per_col: dict[str, list[float]] = {c: [] for c in ["start", *cols]}
        for view in ds.test:
            cam = heldout_camera(est_cams, gt.camera_of(next(n for n in gt.names if Path(n).stem == view)))
            noisy, clean = read_image(ds.images[view]), read_image(ds.clean[view])
            target = torch.as_tensor(noisy).permute(2, 0, 1)

            def loss_and_psnr(pose, cam=cam, clean=clean, target=target, model=model):
                img = render_views(model, [cam], np.asarray(pose)[None, :3])[0]
                loss = float(photometric_loss(torch.as_tensor(img).permute(2, 0, 1), target, ssim_weight=0.2))
                return loss, float(score_images([img], [clean]).psnr_db[0])

            row = {"start": loss_and_psnr(starts[view])}
            t0 = time.perf_counter()
            for s, c in zip(scales, cols[:-1], strict=True):
                row[c] = loss_and_psnr(fit_pose(model, noisy, cam, starts[view], config=PoseFitConfig(lr_scales=(s,))))
            seconds = time.perf_counter() - t0
            row["combined"] = min((row[c] for c in cols[:-1]), key=lambda r: r[0])
            for c, (_, p) in row.items():
                per_col[c].append(p)
            lines.append(f"| {run} | {view} | {row['start'][1]:.2f} | "
                         + " | ".join(f"{row[c][1]:.2f}" for c in cols) + " |")
            print(lines[-1], f"({seconds:.0f} s of fits)", flush=True)
        means.append(f"| {run} | mean | {np.mean(per_col['start']):.2f} | "
                     + " | ".join(f"{np.mean(per_col[c]):.2f}" for c in cols) + " |")
        print(means[-1], flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
