"""Round 1's two alignments side by side: the noisy photos and the denoised ones, against the true cameras.

`AlignSettings.photos="better_of"` (the `default` and `best` presets) aligns the noisy photos (dense cloud
from the denoised ones) and the denoised photos (with the noisy photos' detector), and keeps the alignment
whose camera centres the bundle adjustment determines better (`eval.pipeline.calibration.better_determined`), with
no ground truth. This repeats both alignments for finished runs and prints, for each, what the rule sees (the
median camera-centre standard deviation over the cameras' spacing), the choice, and what the ground truth says
(median rotation error and ATE after a Sim(3) registration), so the rule can be checked on every set.

Usage: .venv/bin/python benchmarks/diag_align_photos.py DATASET RUN_DIR [RUN_DIR ...]
(DATASET: an evaluation dataset folder with `images/` and `sparse/0/`; RUN_DIR: an evaluation's
`runs/SCENE/seedK/product`, whose `round1/denoised/` holds the denoised photos)
"""
import argparse
import dataclasses
from pathlib import Path

import numpy as np

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from eval.evaluate import FOCAL_PRIOR_OK
from eval.pipeline import preset
from eval.pipeline.align_stage import denoised_photos_config
from eval.pipeline.calibration import better_determined, centre_std_over_spacing
from eval.pipeline.stage_settings import round_settings
from mvgeo.align import align_images
from mvgeo.common.errors import AlignmentRefusedError, DisconnectedViewsError
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


def _truth_row(result, truth: dict[str, np.ndarray], names: list[str]) -> str:
    est = {Path(n).stem: v for n, v in result.sparse_model.cam_from_world_by_name().items()}
    pm = compare_poses(est, {k: truth[k] for k in est})
    std = centre_std_over_spacing(result.sparse_model, result.stats, names)
    median = "unknown" if std is None else f"{np.median(list(std.values())):.4f}"
    return f"{median} | {pm.median_rotation_deg:.3f} | {pm.ate.rmse:.4f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    args = ap.parse_args()
    gt = read_sparse_model(args.dataset / "sparse" / "0")
    truth = {Path(n).stem: v for n, v in gt.cam_from_world_by_name().items()}
    base = dataclasses.replace(preset("default"), max_size=None)
    base = dataclasses.replace(base, align=dataclasses.replace(base.align, max_focal_log_std=FOCAL_PRIOR_OK))
    print("| run | photos | centre std / spacing (median) | rot. err. median (deg) | ATE (GT units) | kept |")
    print("|---|---|---|---|---|---|")
    for run in args.runs:
        files = sorted((run / "round1" / "denoised").glob("*.png"))
        names = [f.name for f in files]
        seed = int(run.parent.name.removeprefix("seed")) if run.parent.name.startswith("seed") else 0
        cfg = round_settings(dataclasses.replace(base, seed=seed), 1).align.align
        results = {}
        for photos in ("noisy", "denoised"):
            try:
                if photos == "noisy":
                    results[photos] = align_images([args.dataset / "images" / n for n in names], cfg, names=names,
                                                   cloud_images=files)
                else:
                    results[photos] = align_images(files, denoised_photos_config(cfg), names=names)
            except (AlignmentRefusedError, DisconnectedViewsError) as exc:
                print(f"| {run} | {photos} | refused: {str(exc).splitlines()[0][:80]} | | | |")
        if len(results) == 2:
            keep, _ = better_determined(results["denoised"].sparse_model, results["denoised"].stats,
                                        results["noisy"].sparse_model, results["noisy"].stats, names)
            kept = "denoised" if keep else "noisy"
        else:
            kept = next(iter(results), "none")
        for photos, res in results.items():
            print(f"| {run} | {photos} | {_truth_row(res, truth, names)} | {'**kept**' if photos == kept else ''} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
