"""Evaluation datasets from real photo sets with known cameras, with synthetic noise added.

`dtu_dataset` turns the DTU scan folders kept beside the project (MonoSDF's
384x384 crop: `images/*.png`, `cameras.npz` with `world_mat_i` and
`scale_mat_i`; see ../shared/data/README.md) into the dataset layout
`denoise-gs eval` reads: `images/` (noisy), `clean/`, `split.json`, `sparse/0/`.

Cameras: the projection ``P = world_mat[:3] @ scale_mat`` (world normalised so
that the object fits the unit sphere) is decomposed into ``K [R | t]``; K is
mapped to the 384x384 crop with ``u' = 0.32 (u - 200)``, ``v' = 0.32 v``
(the README's formula) and shifted by +0.5 px to our pixel convention (the
projection uses OpenCV's, top-left pixel centre at 0), then scaled to the
output size. The half-pixel conventions of the original crop are not
documented; held-out poses are refined photometrically in the evaluation
anyway. The ground-truth model has no points, so `3dgs_gt_poses` (which
needs initial points) does not run on it.

Run: ``python -m eval.datasets dtu ../shared/data/dtu_scan24 --out DIR [--sigma 25] [--size 192]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mvgeo.camera import Camera
from mvgeo.common.atomic import atomic_write_text
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, write_image
from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model

__all__ = ["dtu_cameras", "dtu_dataset", "spread_split"]

_CROP = np.array([[0.32, 0.0, -0.32 * 200.0], [0.0, 0.32, 0.0], [0.0, 0.0, 1.0]])


def dtu_cameras(npz_path: Path, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(K at 384x384 in our pixel convention, cam_from_world (3, 4) in the normalised world) per view.

    Raises:
        InputError: a `world_mat_i` / `scale_mat_i` is missing.
    """
    data = np.load(npz_path)
    out = []
    for i in range(n):
        if f"world_mat_{i}" not in data or f"scale_mat_{i}" not in data:
            raise InputError(f"cameras.npz has no world_mat_{i} / scale_mat_{i}", path=npz_path)
        P = (data[f"world_mat_{i}"] @ data[f"scale_mat_{i}"])[:3]
        K, R, c_h = cv2.decomposeProjectionMatrix(P)[:3]
        K = K / K[2, 2]
        if np.linalg.det(R) < 0:
            raise InputError(f"view {i}: projection decomposes to a reflection", path=npz_path)
        C = (c_h[:3] / c_h[3]).reshape(3)
        K384 = _CROP @ K
        K384[0, 2] += 0.5
        K384[1, 2] += 0.5
        out.append((K384, np.hstack([R, (-R @ C)[:, None]])))
    return out


def spread_split(n: int, train: int, test: int) -> tuple[list[int], list[int]]:
    """`train` indices spread evenly over ``0..n-1`` and `test` others, also spread (midway between)."""
    if train + test > n or train < 2 or test < 1:
        raise InputError(f"cannot split {n} views into {train} training and {test} held-out views")
    tr = [int(v) for v in np.unique(np.round(np.linspace(0, n - 1, train)).astype(int))]
    rest = [i for i in range(n) if i not in tr]
    te = [rest[int(v)] for v in np.unique(np.round(np.linspace(0, len(rest) - 1, test + 2)[1:-1]).astype(int))]
    return tr, te


def dtu_dataset(src: str | Path, out: str | Path, *, sigma_8bit: float = 25.0, size_px: int | None = None,
                train_views: int = 12, test_views: int = 4, seed: int = 0) -> Path:
    """Write a noisy evaluation dataset from a DTU scan folder (see the module docstring).

    Args:
        src: folder with `images/*.png` (384x384) and `cameras.npz`.
        out: dataset folder to write (replaced atomically).
        sigma_8bit: Gaussian noise std on the 0..255 scale, added to the clean images (clipped, 8-bit).
        size_px: output side (square crops); None keeps 384.
        train_views, test_views: split sizes, spread over the views.
        seed: noise seed.

    Raises:
        InputError: missing files or a bad split.
    """
    src, out = Path(src), Path(out)
    files = sorted((src / "images").glob("*.png"))
    if not files or not (src / "cameras.npz").is_file():
        raise InputError("not a DTU scan folder (needs images/*.png and cameras.npz)", path=src)
    cams = dtu_cameras(src / "cameras.npz", len(files))
    tr, te = spread_split(len(files), train_views, test_views)
    rng = np.random.default_rng(seed)
    tmp = out.with_name(f".{out.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    for sub in ("images", "clean"):
        (tmp / sub).mkdir(parents=True)
    cameras, images = {}, []
    for i in sorted(tr + te):
        img = read_image(files[i])
        h, w = img.shape[:2]
        K = cams[i][0].copy()
        if size_px is not None and size_px != w:
            s = size_px / w
            img = cv2.resize(img, (size_px, round(h * s)), interpolation=cv2.INTER_AREA)
            K[:2] *= s  # edge-based pixel convention: scaling is exact
            h, w = img.shape[:2]
        name = f"view_{i:03d}.png"
        write_image(tmp / "clean" / name, img)
        clean8 = np.round(img * 255.0) / 255.0
        noisy = np.clip(clean8 + rng.normal(0.0, sigma_8bit / 255.0, img.shape), 0.0, 1.0)
        write_image(tmp / "images" / name, noisy)
        cameras[len(cameras) + 1] = Camera("PINHOLE", w, h, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        images.append(PosedImage(name, len(cameras), cams[i][1]))
    write_sparse_model(tmp / "sparse" / "0", SparseModel(cameras, images), binary=False)
    split = {"train": [f"view_{i:03d}.png" for i in tr], "test": [f"view_{i:03d}.png" for i in te]}
    atomic_write_text(tmp / "split.json", json.dumps(split, indent=2) + "\n")
    atomic_write_text(tmp / "meta.json", json.dumps({"source": str(src), "noise": {"type": "gaussian",
                                                     "sigma_8bit": sigma_8bit, "seed": seed}}, indent=2) + "\n")
    if out.exists():
        old = out.with_name(f".{out.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(out, old)
        shutil.rmtree(old)
    os.replace(tmp, out)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m eval.datasets", description=__doc__.split("\n")[0])
    add_common_args(parser)
    sub = parser.add_subparsers(dest="kind", required=True)
    d = sub.add_parser("dtu", help="DTU scan (MonoSDF crop) -> noisy evaluation dataset")
    d.add_argument("src", type=Path)
    d.add_argument("--out", type=Path, required=True)
    d.add_argument("--sigma", type=float, default=25.0, help="Gaussian noise std on the 0..255 scale")
    d.add_argument("--size", type=int, default=None, help="output side in pixels (default 384)")
    d.add_argument("--train", type=int, default=12)
    d.add_argument("--test", type=int, default=4)
    d.add_argument("--seed", type=int, default=0)

    def run(args: argparse.Namespace) -> int:
        path = dtu_dataset(args.src, args.out, sigma_8bit=args.sigma, size_px=args.size, train_views=args.train,
                           test_views=args.test, seed=args.seed)
        print(f"dataset: {path}")
        return 0

    return run_cli(run, parser, argv)


if __name__ == "__main__":
    raise SystemExit(main())
