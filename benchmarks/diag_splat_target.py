"""Retrain a finished run's round-1 splat on another target and score it held out, as `denoise-gs eval` does.

Everything before the splat (the working photos, the denoised photos, the alignment) is the run's own; only the
splat's training target changes: `--noisy-detail W` trains on ``denoised + w * highpass(noisy - denoised)``
with ``w = W * min(1, (25/255) / sigma)`` (`eval.pipeline.splat_training.noisy_detail_targets`, as the splat stage
builds it; `--fixed-weight`: ``w = W``; `--band-in-dark-clipped`: the band in dark clipped regions too). With
the run's own setting the
splat and the held-out scores repeat the run's to the last digit (checked on `llff_like` seed 0: 25.65 / 0.724 /
0.239 both ways), so a sweep of the target costs one splat training per point instead of a whole run.

The splat's seed is the run's (`stage_seed(SEED, 1, "splat")`) and its settings the preset's. A run with
estimated cameras is scored with the held-out pose fit of `eval`; `--true-cameras GT_RUN` takes the
alignment from a `@gt_poses` variant's folder and scores with the true cameras, as `eval` scores those.

`--render-detail A --render-sigma-px S` adds ``A * fine(render - denoised)`` to every target, `fine` being
everything below a Gaussian of S px and `render` the run's round-1 render of the view (`round1/renders/`): a
round 2 that takes the first splat's detail, as the paper's round-2 loss does (docs/bench/pipeline.md).

Usage: .venv/bin/python benchmarks/diag_splat_target.py DATASET RUN_DIR --seed K --noisy-detail W [W ...]
       [--sigma-px S] [--fixed-weight] [--preset default] [--true-cameras GT_RUN_DIR] [--out DIR]
       [--render-detail A] [--render-sigma-px S]
(DATASET: the evaluation dataset; RUN_DIR: an evaluation's `runs/SCENE/seedK/product`, holding `inputs/`,
`round1/denoised/` and `round1/align/`)
"""
import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from denoise.detail import NoisyDetail
from eval.evaluate import EvalConfig, _score_scene, score_reconstruction
from eval.pipeline.config import PRESETS
from eval.pipeline.inputs import WORKING_DIR
from eval.pipeline.splat_training import noisy_detail_targets
from eval.pipeline.stage_settings import stage_seed, train_config
from eval.pipeline.validate import validate_dataset_folder
from eval.pipeline.views import read_views
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model


def _render_detail(targets: dict[str, np.ndarray], denoised: dict[str, np.ndarray], renders: dict[str, np.ndarray],
                   amount: float, sigma_px: float) -> dict[str, np.ndarray]:
    """Each target plus `amount` times the fine band (below a Gaussian of `sigma_px`) of the run's own round-1
    render minus its denoised photo: the multi-view-consistent detail of the first splat, the paper's round-2
    "detail consistency with the renders" put into the splat's target."""
    from scipy.ndimage import gaussian_filter

    def fine(x):
        return x - gaussian_filter(x, (sigma_px, sigma_px, 0))

    return {k: (t + amount * (fine(renders[k].astype(np.float64)) - fine(denoised[k].astype(np.float64))))
            .astype(np.float32) for k, t in targets.items()}


def _retrain(dataset, run: Path, align_dir: Path, detail: NoisyDetail, seed: int, preset: str, out: Path,
             true_cameras: bool, render_detail: tuple[float, float] | None = None) -> dict[str, float]:
    from splat.ply import read_gaussian_ply, write_gaussian_ply
    from splat.train import train_gaussians

    sparse = read_sparse_model(align_dir / "sparse" / "0")
    pts = np.load(align_dir / "points.npz")
    stems = [n.rsplit(".", 1)[0] for n in sparse.names]
    denoised, noisy = read_views(run / "round1" / "denoised", stems), read_views(run / WORKING_DIR, stems)
    targets, weights = noisy_detail_targets(denoised, noisy, detail)  # as the splat stage builds them
    if render_detail is not None and render_detail[0] != 0:
        renders = read_views(run / "round1" / "renders", stems)
        targets = _render_detail(targets, denoised, renders, *render_detail)
    images = [targets[k] for k in stems]
    cams = [sparse.camera_of(n) for n in sparse.names]
    cam_from_world = np.stack([sparse.image(n).cam_from_world for n in sparse.names])
    config = train_config(PRESETS[preset].splat, seed=stage_seed(seed, 1, "splat"))
    t0 = time.perf_counter()
    res = train_gaussians(images, cams, cam_from_world, pts["xyz"], pts["rgb"], config, device="cpu")
    seconds = time.perf_counter() - t0
    write_gaussian_ply(out / "point_cloud.ply", res.model)
    optimised = [PosedImage(im.name, im.camera_id, np.asarray(res.cam_from_world_optimized[i])[:3])
                 for i, im in enumerate(sparse.images)]
    write_sparse_model(out / "sparse" / "0", SparseModel(sparse.cameras, optimised, sparse.points_xyz,
                                                         sparse.points_rgb), binary=True)
    if true_cameras:  # as `eval` scores a @gt_poses variant: the true cameras, no pose fit
        gt = read_sparse_model(dataset.root / "sparse" / "0")
        per_view, _ = _score_scene(read_gaussian_ply(out / "point_cloud.ply", device="cpu"), gt, None, dataset,
                                   EvalConfig())
        scores = {m: float(np.mean([v[m] for v in per_view.values()])) for m in ("psnr_db", "ssim", "lpips")}
    else:
        scores = score_reconstruction(out, dataset, stems)
    return {**scores, "splat_s": seconds, "weight_min": min(weights.values()), "weight_max": max(weights.values())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("--seed", type=int, required=True, help="the run's evaluation seed")
    ap.add_argument("--noisy-detail", type=float, nargs="+", required=True, help="weights W to train with")
    ap.add_argument("--sigma-px", type=float, default=1.0)
    ap.add_argument("--fixed-weight", action="store_true", help="W on every photo, whatever its noise level")
    ap.add_argument("--band-in-dark-clipped", action="store_true",
                    help="the band in dark clipped regions too (NoisyDetail.skip_dark_clipped=False)")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--true-cameras", type=Path, default=None, help="a @gt_poses variant's run folder")
    ap.add_argument("--out", type=Path, default=None, help="keep the splats here (default: a temporary folder)")
    ap.add_argument("--render-detail", type=float, default=0.0,
                    help="add this fraction of the fine band of (round-1 render - denoised photo) to each target")
    ap.add_argument("--render-sigma-px", type=float, default=2.0, help="the fine band's Gaussian (pixels)")
    args = ap.parse_args()
    dataset = validate_dataset_folder(args.dataset)
    align_dir = (args.true_cameras or args.run) / "round1" / "align"
    with tempfile.TemporaryDirectory() as tmp:
        for w in args.noisy_detail:
            out = (args.out or Path(tmp)) / f"w{w:g}"
            out.mkdir(parents=True, exist_ok=args.out is None)
            reference = None if args.fixed_weight else NoisyDetail().reference_std
            detail = NoisyDetail(w, args.sigma_px, reference, skip_dark_clipped=not args.band_in_dark_clipped)
            row = _retrain(dataset, args.run, align_dir, detail, args.seed, args.preset, out,
                           args.true_cameras is not None, (args.render_detail, args.render_sigma_px))
            print(json.dumps({"run": str(args.run), "seed": args.seed, "noisy_detail": w, "sigma_px": args.sigma_px,
                              "render_detail": args.render_detail, "render_sigma_px": args.render_sigma_px,
                              "band_in_dark_clipped": args.band_in_dark_clipped,
                              **{k: round(v, 4) for k, v in row.items()}}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
