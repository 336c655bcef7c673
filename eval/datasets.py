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

Splits: ``spread`` takes the views evenly over DTU's index range (20-40 deg between neighbours: neither
COLMAP nor our classical matcher connects 12 of them); ``cluster`` takes the most alike views (about
11 deg apart) with interior held-out views.

Run: ``python -m eval.datasets dtu ../shared/data/dtu_scan24 --out DIR [--sigma 25] [--size 192]
[--layout spread|cluster]``.
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

__all__ = ["cluster_split", "dtu_cameras", "dtu_dataset", "spread_split"]

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


def cluster_split(view_dirs_world: np.ndarray, train: int, test: int) -> tuple[list[int], list[int]]:
    """The ``train + test`` views that look most alike, with interior held-out views.

    The cluster is the ``train + test`` views whose viewing directions are closest (in angle) to the
    mean viewing direction of all views. Held-out views are taken greedily from the cluster's centre
    outwards. A view is held out when its training neighbours (within 1.5 times the cluster's median
    nearest-neighbour angle; views already held out do not count) surround it: no gap of 150 deg or more
    between their bearings around it, so that it lies inside the training views. Views with no held-out
    neighbour are taken first, then any that are still surrounded.

    Args:
        view_dirs_world: (N, 3) unit viewing directions (camera +z axes in the world frame).
        train, test: split sizes.

    Returns:
        (training indices, held-out indices), each sorted.

    Raises:
        InputError: the split does not fit, or the interior has too few views for `test`.
    """
    d = np.asarray(view_dirs_world, dtype=np.float64)
    n = len(d)
    if train + test > n or train < 2 or test < 1:
        raise InputError(f"cannot split {n} views into {train} training and {test} held-out views")
    mean = d.mean(axis=0)
    mean /= np.linalg.norm(mean)
    cluster = np.argsort(-(d @ mean), kind="stable")[: train + test]
    dc = d[cluster]
    centre = dc.mean(axis=0)
    angle = np.arccos(np.clip(dc @ dc.T, -1.0, 1.0))
    np.fill_diagonal(angle, np.inf)
    neighbour = angle <= 1.5 * np.median(angle.min(axis=1))
    order = np.argsort(-(dc @ centre), kind="stable")
    held: list[int] = []
    for apart in (True, False):  # first views with no held-out neighbour, then any that are still inside
        for k in order:
            if len(held) == test:
                break
            if k in held or (apart and neighbour[k, held].any()):
                continue
            train_near = [m for m in np.flatnonzero(neighbour[k]) if m not in held]
            if _surrounded(dc[k], dc[train_near]):
                held.append(int(k))
    if len(held) < test:
        raise InputError(f"a cluster of {train + test} views has room for only {len(held)} interior held-out "
                         f"views (asked {test})", fix="hold out fewer views or train on more")
    te = sorted(int(cluster[k]) for k in held)
    tr = sorted(int(i) for i in cluster if int(i) not in te)
    return tr, te


def _surrounded(direction: np.ndarray, others: np.ndarray) -> bool:
    """Whether the directions `others` (K, 3) surround `direction` (3,): all bearing gaps < 150 deg.

    (< 180 deg would admit a view on the segment between two others, on the edge of their hull.)
    """
    if len(others) < 3:
        return False
    helper = np.eye(3)[int(np.argmin(np.abs(direction)))]
    e1 = np.cross(direction, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(direction, e1)
    bearing = np.sort(np.arctan2(others @ e2, others @ e1))
    gaps = np.diff(np.concatenate([bearing, bearing[:1] + 2.0 * np.pi]))
    return bool(gaps.max() < np.radians(150.0))


def dtu_dataset(src: str | Path, out: str | Path, *, sigma_8bit: float = 25.0, size_px: int | None = None,
                train_views: int = 12, test_views: int = 4, seed: int = 0, layout: str = "spread") -> Path:
    """Write a noisy evaluation dataset from a DTU scan folder (see the module docstring).

    Args:
        src: folder with `images/*.png` (384x384) and `cameras.npz`.
        out: dataset folder to write (replaced atomically).
        sigma_8bit: Gaussian noise std on the 0..255 scale, added to the clean images (clipped, 8-bit).
        size_px: output side (square crops); None keeps 384.
        train_views, test_views: split sizes.
        seed: noise seed.
        layout: "spread" (`spread_split`: views spread evenly over the index range, 20-40 deg apart on
            DTU's 49) or "cluster" (`cluster_split`: the most alike views, about 11 deg apart on DTU).

    Raises:
        InputError: missing files or a bad split.
    """
    src, out = Path(src), Path(out)
    files = sorted((src / "images").glob("*.png"))
    if not files or not (src / "cameras.npz").is_file():
        raise InputError("not a DTU scan folder (needs images/*.png and cameras.npz)", path=src)
    cams = dtu_cameras(src / "cameras.npz", len(files))
    if layout == "spread":
        tr, te = spread_split(len(files), train_views, test_views)
    elif layout == "cluster":
        tr, te = cluster_split(np.array([cam_from_world[2, :3] for _, cam_from_world in cams]), train_views,
                               test_views)
    else:
        raise InputError(f"unknown split layout {layout!r}", fix='use "spread" or "cluster"')
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
    atomic_write_text(tmp / "meta.json", json.dumps({"source": str(src), "layout": layout,
                                                     "noise": {"type": "gaussian", "sigma_8bit": sigma_8bit,
                                                               "seed": seed}}, indent=2) + "\n")
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
    d.add_argument("--layout", choices=("spread", "cluster"), default="spread",
                   help="spread: views spread over the index range; cluster: the most alike views")

    def run(args: argparse.Namespace) -> int:
        path = dtu_dataset(args.src, args.out, sigma_8bit=args.sigma, size_px=args.size, train_views=args.train,
                           test_views=args.test, seed=args.seed, layout=args.layout)
        print(f"dataset: {path}")
        return 0

    return run_cli(run, parser, argv)


if __name__ == "__main__":
    raise SystemExit(main())
