"""BM3D's photos as splat training photos: the classical reference denoiser, written out for
`benchmarks/diag_splat_inputs.py` (`dir:OUT/bm3d`, `dir:OUT/bm3d_unclip`).

BM3D (PyPI `bm3d`, the `bench` group: free for non-commercial use only, so never a product dependency)
with the true sigma on each noisy photo; `bm3d_unclip/` also maps each output through the inverse of the
clipped-noise mean on the sides where its noisy photo is clipped (`denoise.clipping.undo_clipping_bias`,
as the product's R2R output is): BM3D's additive-noise model returns the mean of the clipped photo, biased
near black and white. Prints the photos' PSNR against the clean ones, in all, where the clean photo is
dark (< 0.03), bright (> 0.97) and in between ("textured"), for both and for `--compare` folders.

Usage: .venv/bin/python benchmarks/diag_bm3d_photos.py NOISY_DIR CLEAN_DIR OUT --sigma 25 [--compare DIR...]
"""
import argparse
import time
from pathlib import Path

import numpy as np

# isort: off
import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
import torch
# isort: on

from denoise.self_supervised import _undo_clipping
from mvgeo.common.imageio import read_image, write_image


def _split_psnr(photos: dict[str, np.ndarray], clean_dir: Path) -> str:
    parts = {"all": [], "dark": [], "bright": [], "textured": []}
    for name, d in photos.items():
        c = read_image(clean_dir / name).astype(np.float64)
        err = (np.asarray(d, np.float64) - c) ** 2
        grey = c.mean(axis=-1)
        masks = {"all": np.ones_like(grey, bool), "dark": grey < 0.03, "bright": grey > 0.97}
        masks["textured"] = ~masks["dark"] & ~masks["bright"]
        for k, m in masks.items():
            parts[k].append(err[m])
    return ", ".join(f"{k} {10 * np.log10(1.0 / np.concatenate(v).mean()):.2f}" for k, v in parts.items())


def main() -> int:
    import bm3d  # the bench group

    ap = argparse.ArgumentParser()
    ap.add_argument("noisy_dir", type=Path)
    ap.add_argument("clean_dir", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--sigma", type=float, required=True, help="the true noise std, in 1/255")
    ap.add_argument("--compare", type=Path, nargs="*", default=[])
    args = ap.parse_args()
    sigma = args.sigma / 255.0
    names = sorted(p.name for p in args.noisy_dir.iterdir() if p.suffix == ".png")
    noisy = [read_image(args.noisy_dir / n) for n in names]
    t = time.perf_counter()
    plain = [np.clip(bm3d.bm3d_rgb(y, sigma_psd=sigma), 0, 1).astype(np.float32) for y in noisy]
    seconds = (time.perf_counter() - t) / len(names)
    # The denoise stage's own correction of a network's output (`denoise_with_method`), at the true sigma.
    sigmas = [torch.tensor(sigma, dtype=torch.float32)] * len(names)
    unclip = [np.clip(x, 0, 1).astype(np.float32) for x in _undo_clipping(noisy, plain, sigmas, clean_sigma=0.0)]
    for kind, photos in (("bm3d", plain), ("bm3d_unclip", unclip)):
        (args.out / kind).mkdir(parents=True, exist_ok=False)
        for n, x in zip(names, photos, strict=True):
            write_image(args.out / kind / n, x)
        print(f"{kind}: {_split_psnr(dict(zip(names, photos, strict=True)), args.clean_dir)}")
    print(f"BM3D: {seconds:.1f} s per photo")
    for folder in args.compare:
        print(f"{folder}: {_split_psnr({n: read_image(folder / n) for n in names}, args.clean_dir)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
