"""The `default` preset's evaluation with the alignment's dense cloud made of other photos than the splat's.

The `default` preset splats the denoised photos refined by the DCT Wiener step, and its alignment's dense
cloud (the stereo's flows and colours, the splat's start) is made of the same refined photos. This runs
`denoise-gs eval DATASET --preset default --seeds 1 --methods product` (seed 0) in this process with
`mvgeo.align.align_images` wrapped so that the cloud is made of the same-named photos in PILOT_DIR
instead: e.g. the network's own
photos of seed 0 of an evaluation without the step (`OUT/runs/SCENE/seed0/product/round1/denoised`, made
before the step existed: the same network). Everything else, the splat's training photos included, is the
preset's. Fresh OUT.

Usage: .venv/bin/python benchmarks/diag_wiener_stereo.py DATASET PILOT_DIR OUT
"""
import argparse
import sys
from pathlib import Path

import eval.cli  # first: sets the thread policy before torch loads
import mvgeo.align


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("pilot_dir", type=Path)
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    original = mvgeo.align.align_images

    def cloud_from_pilots(images, *a, cloud_images=None, **kw):
        if cloud_images is not None:
            cloud_images = [args.pilot_dir / Path(f).name for f in cloud_images]
            missing = [p for p in cloud_images if not p.is_file()]
            if missing:
                raise SystemExit(f"{args.pilot_dir} lacks {missing[0].name}")
        return original(images, *a, cloud_images=cloud_images, **kw)

    mvgeo.align.align_images = cloud_from_pilots  # the align stage imports it from the package when it runs
    return eval.cli.main(["eval", str(args.dataset), "--out", str(args.out), "--preset", "default", "--seeds", "1",
                          "--methods", "product"])


if __name__ == "__main__":
    sys.exit(main())
