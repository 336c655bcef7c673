"""`denoise-gs dataset import FORMAT SRC --out DIR ...`: the command line of `eval.real.import_dataset`."""

from __future__ import annotations

import argparse

from eval.real.api import KINDS, import_dataset
from mvgeo.common.argtypes import int_range, out_path, positive_int, seed, size_wh
from mvgeo.common.output import OUT_HELP, OVERWRITE_HELP

__all__ = ["add_dataset_parser"]


def _cmd_import(args: argparse.Namespace) -> int:
    path = import_dataset(args.format, args.src, args.out, views=args.views, test_every=args.test_every,
                          test=args.test, noise=args.noise, seed=args.seed, layout=args.layout, size_wh=args.size,
                          max_size_px=args.max_size, llff_factor=args.factor, overwrite=args.overwrite)
    print(f"dataset: {path}")
    return 0


def add_dataset_parser(sub: argparse._SubParsersAction) -> None:
    """Register `dataset import` on a `denoise-gs` subparsers object (sets `func`)."""
    ds = sub.add_parser("dataset", help="make evaluation datasets from real photographs with known cameras")
    ds_sub = ds.add_subparsers(dest="dataset_command", required=True)
    imp = ds_sub.add_parser(
        "import", help="real capture (LLFF, COLMAP, Middlebury, DTU) -> dataset folder with declared noise",
        description="Read a photographed scene with ground-truth cameras and write the dataset layout "
                    "(images/, clean/, split.json, sparse/0/, meta.json). images/ gets exactly the declared "
                    "--noise (none by default: byte-identical to clean/).")
    imp.add_argument("format", choices=KINDS,
                     help="llff: poses_bounds.npy + images[_N]/; colmap: sparse/0 + images/; middlebury: "
                          "*_par.txt (or its folder); dtu: cameras.npz + images/")
    imp.add_argument("src", help="the capture folder (or the Middlebury *_par.txt file)")
    imp.add_argument("--out", type=out_path, required=True, help=OUT_HELP)
    imp.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    imp.add_argument("--noise", default=None, metavar="SPEC",
                     help="none (default), gaussian:SIGMA_8BIT (e.g. gaussian:25 = 25/255), "
                          "poisson-gaussian:GAIN,READ_SIGMA_8BIT (Var = GAIN x + (READ/255)^2, x in [0, 1]), or "
                          "bayer-pg:GAIN,READ_SIGMA_8BIT (that noise on a Bayer mosaic, then demosaiced: "
                          "correlated between neighbouring pixels, as in a camera's photos), jpeg:QUALITY (a "
                          "JPEG round trip), or steps joined by + and applied in order (e.g. "
                          "bayer-pg:0.01,5+jpeg:90: a camera's noisy photo as it stores it)")
    imp.add_argument("--seed", type=seed, default=0, help="noise seed (default 0)")
    imp.add_argument("--views", type=int_range(2), default=None,
                     help="training views, spread over the candidates (default: all that are not held out)")
    imp.add_argument("--test-every", type=int_range(2), default=None, metavar="K",
                     help="hold out views 0, K, 2K, ... (LLFF's convention; default 8)")
    imp.add_argument("--test", type=positive_int, default=None, metavar="N",
                     help="hold out N views instead, midway between the training views")
    imp.add_argument("--layout", choices=("spread", "cluster", "ring"), default="spread",
                     help="spread (default): views over the capture's order; cluster: the most alike viewing "
                          "directions, held-out views inside them (--test N, default 4); ring: an orbit, training "
                          "views spread by angle around the cameras' ring (--views, default 12), held out the "
                          "views between them (all, or --test N)")
    size = imp.add_mutually_exclusive_group()
    size.add_argument("--size", type=size_wh(min_px=8, max_px=8192), default=None, metavar="WxH",
                      help="resize every image to WxH (area filter; intrinsics scaled exactly)")
    size.add_argument("--max-size", type=int_range(8), default=None, metavar="PX",
                      help="downscale so that the longer side is at most PX")
    imp.add_argument("--factor", type=positive_int, default=None, metavar="N",
                     help="LLFF only: read images_N/ (LLFF's downsampled copies) instead of images/")
    imp.set_defaults(func=_cmd_import)
