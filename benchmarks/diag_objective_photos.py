"""The denoising objectives on a dataset's whole training photos, by region: where the noise is clipped at
black (or white), and elsewhere.

Trains the `default` preset's UNet (2000 steps) with one objective on the noisy training photos of a dataset
folder (`images/`, `clean/`, `split.json`), as the pipeline's denoise stage does (`train_with_method`, then
`denoise_with_method` with its defaults: 8 passes, the clipped-noise inverse), writes the photos to OUT, and
prints PSNR / SSIM against `clean/` over the whole photos and PSNR over two regions: pixels whose 4-px
neighbourhood has at least 40 % of its values clipped (at 0 or 1, in some channel) and the rest. Also the
share of the area that is dark and clipped (`denoise.clipping.dark_clipped_fraction`, what
`denoise.self_supervised.choose_objective` reads).

`--checkpoint` scores a model already trained (e.g. a pipeline run's `round1/n2v_model.pt`) instead of
training one; `--dihedral K` (neighbor2neighbor) averages the network over the first K of the 8
rotations / reflections of each photo before the inverse, in place of the one pass the product makes.
The printout also gives the output's mean and median where the clean photo is black (at most 1/255, in
/255): the background level a splat of these photos inherits.

`--width W` / `--batch B` train a wider UNet (first-level channels, the preset's 16) or on larger batches
(the preset's 8 patches of 64 px) with the same steps and schedule: what the network's size buys.

`bm3d` is the classical reference on the same photos: BM3D (`bm3d.bm3d_rgb`, one thread) given the true
noise std `--sigma` (in /255), photo by photo.

Usage: .venv/bin/python benchmarks/diag_objective_photos.py DATASET OUT r2r|neighbor2neighbor|n2v [--seed N]
           [--width W] [--batch B]
       .venv/bin/python benchmarks/diag_objective_photos.py DATASET OUT bm3d --sigma 25
       .venv/bin/python benchmarks/diag_objective_photos.py DATASET OUT score   (photos already in OUT)
"""

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from denoise.clipping import DARK_CLIPPED_BLUR_PX, DARK_CLIPPED_MIN_LOCAL, dark_clipped_fraction
from denoise.model import load_checkpoint
from denoise.n2v import n2v_preset
from denoise.self_supervised import denoise_with_method, train_with_method
from eval.pipeline.views import read_views, write_views
from mvgeo.common.deps import cv2
from mvgeo.image_metrics import ssim

STEPS = 2000


def _ssim(a: np.ndarray, b: np.ndarray) -> float:
    import torch

    t = lambda x: torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float64))[None]  # noqa: E731
    return float(ssim(t(a), t(b)))


def _psnr(err: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean(err)))


def score(dataset: Path, photos: dict[str, np.ndarray]) -> dict[str, float]:
    noisy, clean = read_views(dataset / "images"), read_views(dataset / "clean")
    rows = []
    for name, out in photos.items():
        y, c = noisy[name], clean[name]
        clipped = ((y <= 0) | (y >= 1)).astype(np.float32)
        region = (cv2.GaussianBlur(clipped, (0, 0), DARK_CLIPPED_BLUR_PX) >= DARK_CLIPPED_MIN_LOCAL).any(axis=2)
        err = np.mean((out.astype(np.float64) - c) ** 2, axis=2)
        rows.append([_psnr(err), _ssim(out, c), _psnr(err[region]) if region.any() else np.nan,
                     _psnr(err[~region]), float(region.mean()), dark_clipped_fraction(y)])
    m = np.nanmean(np.array(rows), axis=0)
    black = np.concatenate([photos[n][clean[n].max(axis=2) <= 1 / 255] for n in photos]).ravel() * 255
    return {**dict(zip(["psnr", "ssim", "psnr_clipped_regions", "psnr_elsewhere", "clipped_area",
                        "dark_clipped_area"], (float(v) for v in m), strict=True)),
            "black_mean_255": float(black.mean()) if black.size else float("nan"),
            "black_median_255": float(np.median(black)) if black.size else float("nan")}


def _dihedral_n2n(model, images: list[np.ndarray], k: int) -> list[np.ndarray]:
    """Neighbor2Neighbor's output averaged over `k` dihedral views of each photo, then the clipped-noise
    inverse as `denoise_with_method` applies it."""
    import torch

    from denoise import self_supervised as S
    from denoise.images import image_to_tensor, tensor_to_image
    from denoise.inference import dihedral, predict_tiled

    model.unet.eval()
    out = []
    with torch.no_grad():
        for img in images:
            x = image_to_tensor(img)[None]
            y = sum(dihedral(predict_tiled(model, dihedral(x, d), tile_px=S.TILE_PX, margin_px=S.MARGIN_PX), d,
                             inverse=True) for d in range(k))
            out.append(tensor_to_image(y[0] / k, like=img))
    sig = [torch.as_tensor(v, dtype=torch.float32) for v in S._sigmas(images, None, "auto")]
    return S._undo_clipping(images, out, sig, S.CLEAN_SIGMA)


def _bm3d_photos(dataset: Path, stems: list[str], sigma: float) -> dict[str, np.ndarray]:
    import time

    import bm3d

    profile = bm3d.BM3DProfile()
    profile.num_threads = 1
    noisy, out = read_views(dataset / "images"), {}
    t = time.perf_counter()
    for s in stems:
        out[s] = np.clip(bm3d.bm3d_rgb(noisy[s], sigma, profile=profile), 0, 1).astype(np.float32)
    print(f"bm3d: {(time.perf_counter() - t) / len(stems):.1f} s per photo", file=sys.stderr)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("method", choices=["r2r", "neighbor2neighbor", "n2v", "bm3d", "score"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sigma", type=float, default=None, help="bm3d: the true noise std, in /255")
    ap.add_argument("--checkpoint", type=Path, default=None, help="a trained model to use instead of training")
    ap.add_argument("--dihedral", type=int, default=1, help="neighbor2neighbor: passes over the 8 dihedral views")
    ap.add_argument("--width", type=int, default=None, help="the UNet's first-level channels (preset: 16)")
    ap.add_argument("--batch", type=int, default=None, help="training patches per step (preset: 8)")
    args = ap.parse_args()
    train = json.loads((args.dataset / "split.json").read_text())["train"]
    stems = [Path(n).stem for n in train]
    if args.sigma is not None and args.method != "bm3d":
        ap.error("--sigma is for bm3d only")
    if args.dihedral != 1 and (args.method != "neighbor2neighbor" or not 1 <= args.dihedral <= 8):
        ap.error("--dihedral K: neighbor2neighbor only, 1 <= K <= 8")
    if (args.width is not None or args.batch is not None) and (args.method in ("bm3d", "score") or args.checkpoint):
        ap.error("--width / --batch set the network to train: not with bm3d, score or --checkpoint")
    if any(v is not None and v < 1 for v in (args.width, args.batch)):
        ap.error("--width and --batch must be at least 1")
    if args.method == "bm3d":
        if args.sigma is None:
            ap.error("bm3d needs --sigma (the true noise std, in /255)")
        write_views(args.out, _bm3d_photos(args.dataset, stems, args.sigma / 255.0))
    elif args.method != "score":
        noisy = read_views(args.dataset / "images")
        images = [noisy[s] for s in stems]
        cfg = replace(n2v_preset("default", steps=STEPS), method=args.method)
        if args.width is not None:
            cfg = replace(cfg, unet=replace(cfg.unet, width=args.width))
        if args.batch is not None:
            cfg = replace(cfg, batch_size=args.batch)
        model = load_checkpoint(args.checkpoint) if args.checkpoint else train_with_method(images, cfg, seed=args.seed)
        if args.dihedral > 1 and args.method == "neighbor2neighbor":
            out = _dihedral_n2n(model, images, args.dihedral)
        else:
            out = denoise_with_method(model, images, cfg, passes=8, seed=args.seed)
        write_views(args.out, dict(zip(stems, out, strict=True)))
    photos = read_views(args.out)
    print(json.dumps({"dataset": str(args.dataset), "photos": str(args.out), "method": args.method,
                      **score(args.dataset, {s: photos[s] for s in stems})}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
