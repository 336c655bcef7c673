"""DTU scan -> noisy evaluation dataset: the `python -m eval.datasets dtu` entry point.

A thin front of `eval.real` (`denoise-gs dataset import dtu` is the general
command, with every format and noise model). `dtu_dataset` imports a DTU scan
folder (MonoSDF's 384x384 crop: `images/*.png`, `cameras.npz`; see
`eval.real.dtu` for the camera conversion) with Gaussian noise of
`sigma_8bit` on the 0..255 scale and the `spread` or `cluster` split
(`eval.real.split`).

Run: ``python -m eval.datasets dtu ../shared/data/dtu_scan24 --out DIR [--sigma 25] [--size 192]
[--layout spread|cluster] [--overwrite]``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from eval.real.api import import_dataset
from eval.real.dtu import dtu_cameras
from eval.real.split import cluster_split, spread_split
from mvgeo.common.argtypes import out_path
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.output import OUT_HELP, OVERWRITE_HELP

__all__ = ["cluster_split", "dtu_cameras", "dtu_dataset", "spread_split"]


def dtu_dataset(src: str | Path, out: str | Path, *, sigma_8bit: float = 25.0, size_px: int | None = None,
                train_views: int = 12, test_views: int = 4, seed: int = 0, layout: str = "spread",
                overwrite: bool = True) -> Path:
    """Write a noisy evaluation dataset from a DTU scan folder.

    Args:
        src: folder with `images/*.png` (384x384) and `cameras.npz`.
        out: dataset folder to write (atomically; `mvgeo.common.output` policy).
        sigma_8bit: Gaussian noise std on the 0..255 scale (0: no noise, images/ == clean/).
        size_px: output side in pixels (square images); None keeps the source size.
        train_views, test_views: split sizes.
        seed: noise seed.
        layout: "spread" (views spread evenly over the index range, 20-40 deg apart on DTU's 49) or
            "cluster" (the most alike views, about 11 deg apart on DTU).
        overwrite: replace a previous import at `out` (never anything else).

    Raises:
        InputError: missing files, a bad split, or an `out` the policy refuses.
    """
    noise = "none" if sigma_8bit == 0 else f"gaussian:{sigma_8bit:g}"
    return import_dataset("dtu", src, out, views=train_views, test=test_views, noise=noise, seed=seed,
                          layout=layout, size_wh=None if size_px is None else (size_px, size_px),
                          overwrite=overwrite)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m eval.datasets", description=__doc__.split("\n")[0])
    add_common_args(parser)
    sub = parser.add_subparsers(dest="kind", required=True)
    d = sub.add_parser("dtu", help="DTU scan (MonoSDF crop) -> noisy evaluation dataset")
    d.add_argument("src", type=Path)
    d.add_argument("--out", type=out_path, required=True, help=OUT_HELP)
    d.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    d.add_argument("--sigma", type=float, default=25.0, help="Gaussian noise std on the 0..255 scale")
    d.add_argument("--size", type=int, default=None, help="output side in pixels (default 384)")
    d.add_argument("--train", type=int, default=12)
    d.add_argument("--test", type=int, default=4)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--layout", choices=("spread", "cluster"), default="spread",
                   help="spread: views spread over the index range; cluster: the most alike views")

    def run(args: argparse.Namespace) -> int:
        path = dtu_dataset(args.src, args.out, sigma_8bit=args.sigma, size_px=args.size, train_views=args.train,
                           test_views=args.test, seed=args.seed, layout=args.layout, overwrite=args.overwrite)
        print(f"dataset: {path}")
        return 0

    return run_cli(run, parser, argv)


if __name__ == "__main__":
    raise SystemExit(main())
