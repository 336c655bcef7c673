"""What the splat makes of its training photos' quality: photos of several kinds splatted with the true cameras.

With the poses held at the ground truth and every run starting from the same points (the clean photos'
alignment points on the true cameras' rays, as the `@gt_poses` rows of `denoise-gs eval`), the held-out
scores differ only by the training photos. The kinds:

- `clean`: the clean photos; `clean+noise:S`: the clean photos plus Gaussian noise of sigma S/255 (fixed
  seed), i.e. an unbiased photo of a chosen noise level;
- `noisy`: the evaluation's noisy training photos;
- `round1:SUB[:A]`: A x the product's round-1 photos in `n2v_fused/round1/SUB` (`denoised`, `fused`,
  `noisy_renders`) + (1 - A) x the noisy photo (A defaults to 1);
- `dir:PATH`: any folder holding the training views under their names (e.g. `denoise n2v --method
  neighbor2neighbor --out D` on the noisy photos, then `dir:D/images`).

Usage: .venv/bin/python benchmarks/diag_splat_inputs.py SEED_DIR DATASET OUT --splat-iters N KIND...
(SEED_DIR: an evaluation's `runs/SCENE/seedK` folder that holds `instantsplat/` (its `inputs/` are the noisy
photos), `oracle_clean/` and, for `round1:`, `n2v_fused/`; DATASET: the dataset folder at the evaluation's
working size; OUT: a new folder for the photos and splats). Prints one row per kind.
"""
import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
from _common import held_out_at_true_poses

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from eval.methods import METHODS, ORACLE_CLEAN, _splat_on_ground_truth, gt_pose_variant
from eval.pipeline import preset
from eval.pipeline.validate import validate_dataset_folder
from mvgeo.common.imageio import read_image, write_image

ap = argparse.ArgumentParser()
ap.add_argument("seed_dir", type=Path)
ap.add_argument("dataset", type=Path)
ap.add_argument("out", type=Path)
ap.add_argument("kinds", nargs="+")
ap.add_argument("--splat-iters", type=int, required=True)
args = ap.parse_args()
dataset = validate_dataset_folder(args.dataset)
base = preset("default", views=min(12, len(dataset.train)))
base = dataclasses.replace(base, max_size=None, seed=0, splat=dataclasses.replace(base.splat, iters=args.splat_iters))
variant = gt_pose_variant(METHODS["instantsplat"], ORACLE_CLEAN)
noisy_dir = args.seed_dir / "instantsplat" / "inputs"
names = sorted(p.name for p in noisy_dir.glob("*.png"))


def photo(kind: str, name: str, rng: np.random.Generator) -> np.ndarray:
    noisy = read_image(noisy_dir / name)
    head, _, rest = kind.partition(":")
    if head == "clean":
        return read_image(dataset.root / "clean" / name)
    if head == "clean+noise":
        clean = read_image(dataset.root / "clean" / name)
        return clean + rng.normal(0.0, float(rest) / 255.0, clean.shape)
    if head == "noisy":
        return noisy
    if head == "round1":
        sub, _, a = rest.partition(":")
        a = float(a or 1.0)
        return a * read_image(args.seed_dir / "n2v_fused" / "round1" / sub / name) + (1.0 - a) * noisy
    if head == "dir":
        return read_image(Path(rest) / name)
    sys.exit(f"unknown kind {kind!r}: clean, clean+noise:S, noisy, round1:SUB[:A] or dir:PATH")


# The variant's own config sets InstantSplat's splat length (`eval.methods.paper_loop`): --splat-iters is
# applied after it, so that it is the length trained.
config = variant.pipeline_config(base)
config = dataclasses.replace(config, splat=dataclasses.replace(config.splat, iters=args.splat_iters))
print(f"splat: {config.splat.iters} iterations, the noisy photos' band at weight {config.splat.noisy_detail}",
      flush=True)
print("| training photos | PSNR | SSIM | LPIPS |\n|---|---|---|---|", flush=True)
for k, kind in enumerate(args.kinds):
    folder = args.out / f"{k:02d}"
    (folder / "photos").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(7)
    for name in names:
        write_image(folder / "photos" / name, np.clip(photo(kind, name, rng), 0.0, 1.0).astype(np.float32))
    rec = _splat_on_ground_truth(variant.stages(dataset), config, dataset, folder / "photos",
                                 folder / "run", estimate=args.seed_dir / ORACLE_CLEAN.folder() / "round1")
    m = held_out_at_true_poses(rec.round_dir, dataset)
    print(f"| {kind} | {m['psnr_db']:.2f} | {m['ssim']:.3f} | {m['lpips']:.3f} |", flush=True)
