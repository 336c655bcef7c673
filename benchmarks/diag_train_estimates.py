"""Score estimates of the clean *training* images against `clean/`, and the mean of two of them.

Each FOLDER holds one image per training view (`<stem>.png`, e.g. a round's `denoised/` or `renders/`);
`noisy` stands for the dataset's own `images/`. Prints PSNR / SSIM / LPIPS (`eval.image_metrics`)
averaged over the views the first folder holds. `--mean A B` also scores the per-pixel mean of two of
them (`eval.pipeline.fuse_stage.fuse_images`), and `--write-mean DIR` writes that mean into a copy of the
dataset whose training images are replaced by it (held-out images untouched), for `denoise-gs eval`.

Run: `.venv/bin/python benchmarks/diag_train_estimates.py DATA NAME=FOLDER ... [--mean NAME NAME]
[--write-mean OUT_DATASET]`; the 2026-11-22 table (CHANGELOG.md) used
DATA = `runs/eval7/llff_like/data/llff_like_256x192_14v`, `b=.../seed0/instantsplat/round1/renders`,
`d=.../seed0/n2v/round1/denoised`, `d_render=.../seed0/n2v/round1/renders`, `--mean b d`.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np

from eval.image_metrics import score_images
from eval.pipeline.fuse_stage import fuse_images
from eval.pipeline.validate import validate_dataset_folder
from mvgeo.common.cli import run_cli
from mvgeo.common.deps import cv2  # noqa: F401  (cv2 before anything that imports pycolmap)
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, write_image


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", type=Path, help="dataset folder (images/, clean/, split.json, sparse/0/)")
    ap.add_argument("folders", nargs="+", metavar="NAME=FOLDER", help="estimates to score; NAME=noisy alone "
                                                                       "scores the dataset's noisy images")
    ap.add_argument("--mean", nargs=2, metavar="NAME", help="also score the mean of these two estimates")
    ap.add_argument("--write-mean", type=Path, metavar="OUT_DATASET",
                    help="write a dataset copy whose training images are that mean")
    return ap


def main(args: argparse.Namespace) -> int:
    if args.write_mean and not args.mean:
        raise InputError("--write-mean needs --mean A B")
    ds = validate_dataset_folder(args.data)
    folders = {}
    for item in args.folders:
        name, _, folder = item.partition("=")
        folders[name] = None if name == "noisy" and not folder else Path(folder)
    first = next((f for f in folders.values() if f is not None), None)
    stems = sorted(p.stem for p in first.glob("*.png")) if first else list(ds.train)
    if not stems:
        raise InputError("no <stem>.png images", path=first)

    def load(name: str) -> list[np.ndarray]:
        folder = folders[name]
        if folder is None:
            return [read_image(ds.images[s]) for s in stems]
        missing = [s for s in stems if not (folder / f"{s}.png").is_file()]
        if missing:
            raise InputError(f"{name}: no image for {missing}", path=folder)
        return [read_image(folder / f"{s}.png") for s in stems]

    clean = [read_image(ds.clean[s]) for s in stems]
    estimates = {name: load(name) for name in folders}
    if args.mean:
        a, b = args.mean
        for name in (a, b):
            if name not in estimates:
                raise InputError(f"--mean names {name!r}, which is not among the folders", fix="name it as NAME=FOLDER")
        estimates[f"mean({a}, {b})"] = [fuse_images(x, y) for x, y in zip(estimates[a], estimates[b], strict=True)]
    print(f"{len(stems)} training views against {args.data / 'clean'}")
    print("| estimate | PSNR (dB) | SSIM | LPIPS |\n|---|---|---|---|")
    for name, imgs in estimates.items():
        sc = score_images(imgs, clean)
        print(f"| {name} | {np.mean(sc.psnr_db):.2f} | {np.mean(sc.ssim):.3f} | {np.mean(sc.lpips):.3f} |")
    if args.write_mean:
        tmp = args.write_mean.with_name(args.write_mean.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(args.data, tmp)
        for s, img in zip(stems, estimates[f"mean({args.mean[0]}, {args.mean[1]})"], strict=True):
            write_image(tmp / "images" / ds.images[s].name, img)
        shutil.rmtree(args.write_mean, ignore_errors=True)
        tmp.rename(args.write_mean)
        print(f"dataset with the mean as its training images: {args.write_mean}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main, build_parser()))
