"""The DCT Wiener step (`denoise.wiener`) on a denoiser's photos: how much it adds, by block size and step.

Takes the noisy photos, a folder of their denoised versions (the pilots: e.g. an evaluation's
`product/round1/denoised`, the `default` preset's R2R photos after the clipping correction, written before
the step was part of the preset) and the clean photos. For each variant `BLOCKxSTEP`, every noisy photo is
filtered with the Wiener gains of its pilot at the noise std given (`--sigma`, in 1/255) or the one the
denoise stage estimates (`denoise.self_supervised.r2r_noise_std`), by the denoise stage's own step
(`denoise.self_supervised._refined`), then mapped through the clipped-noise
inverse on the sides where the noisy photo is clipped (`_undo_clipping`, as the denoise stage does after
the step). Prints the photos' PSNR in all, dark, bright and textured (`diag_bm3d_photos._split_psnr`) and
the seconds per photo; with `--write OUT`, writes each variant's photos to `OUT/BLOCKxSTEP/` (for
`benchmarks/diag_splat_inputs.py ... dir:OUT/8x2`). The variant `pilot` is the pilots as they are.

With `--grouped`, each variant's photos are then refined by the grouped Wiener step
(`denoise.grouped_wiener`) as the denoise stage runs it (`_then_grouped`: the variant's photos as pilots,
the clipped-noise inverse after), once per `--grouped-settings` `PATCHxGROUPxSTRIDE` (default `5x40x3`, the
step's own configuration), printed as `VARIANT+grouped SETTING` (written to `OUT/VARIANT+grouped SETTING/`).

Usage: .venv/bin/python benchmarks/diag_wiener_photos.py NOISY_DIR PILOT_DIR CLEAN_DIR [--sigma 25]
           [--write OUT] [--variants BLOCKxSTEP|pilot ...] [--grouped [--grouped-settings 5x40x3 ...]]
           (default variants: 8x2 8x1 12x2 6x1)
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

# isort: off
import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
import torch
# isort: on

from diag_bm3d_photos import _split_psnr  # noqa: E402

from denoise.grouped_wiener import GroupedWienerConfig  # noqa: E402
from denoise.self_supervised import _grouped, _refined, _undo_clipping, r2r_noise_std  # noqa: E402
from denoise.wiener import WienerConfig  # noqa: E402
from mvgeo.common.imageio import read_image, write_image  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("noisy_dir", type=Path)
    ap.add_argument("pilot_dir", type=Path)
    ap.add_argument("clean_dir", type=Path)
    ap.add_argument("--variants", nargs="+", default=["8x2", "8x1", "12x2", "6x1"], help="BLOCKxSTEP ...")
    ap.add_argument("--sigma", type=float, default=None, help="the noise std in 1/255 (default: estimated)")
    ap.add_argument("--write", type=Path, default=None)
    ap.add_argument("--grouped", action="store_true", help="also each variant then the grouped Wiener step")
    ap.add_argument("--grouped-settings", nargs="+", default=["5x40x3"],
                    help="with --grouped: PATCHxGROUPxSTRIDE settings of the grouped step (default 5x40x3, the step's)")
    args = ap.parse_args()
    names = sorted(p.name for p in args.pilot_dir.iterdir() if p.suffix == ".png")
    noisy = [read_image(args.noisy_dir / n) for n in names]
    pilots = [read_image(args.pilot_dir / n) for n in names]
    stds = [args.sigma / 255.0 if args.sigma is not None else r2r_noise_std(y) for y in noisy]
    sig_t = [torch.as_tensor(s, dtype=torch.float32) for s in stds]
    print(f"pilot: {_split_psnr(dict(zip(names, pilots, strict=True)), args.clean_dir)}")
    print(f"noisy: {_split_psnr(dict(zip(names, noisy, strict=True)), args.clean_dir)}")

    def report(name: str, photos: list[np.ndarray], seconds: float) -> None:
        scores = _split_psnr(dict(zip(names, photos, strict=True)), args.clean_dir)
        print(f"{name}: {scores}; {seconds:.2f} s per photo", flush=True)
        if args.write is not None:
            (args.write / name).mkdir(parents=True, exist_ok=False)
            for n, x in zip(names, photos, strict=True):
                write_image(args.write / name / n, x)

    for v in args.variants:
        t = time.perf_counter()
        if v == "pilot":
            photos = pilots
        else:
            block, step = (int(x) for x in v.split("x"))
            cfg = WienerConfig(block_px=block, step_px=step)
            refined = _refined(noisy, pilots, sig_t, 0.0, cfg)  # the denoise stage's own step
            photos = [np.clip(x, 0, 1) for x in _undo_clipping(noisy, refined, sig_t, clean_sigma=0.0)]
        report(v, photos, (time.perf_counter() - t) / len(names))
        for setting in (args.grouped_settings if args.grouped else []):
            p, n, st = (int(x) for x in setting.split("x"))
            t = time.perf_counter()
            gcfg = GroupedWienerConfig(patch_px=p, group_size=n, stride_px=st)
            grouped = _grouped(noisy, photos, sig_t, 0.0, gcfg, clipped_domain=True)  # `_then_grouped`
            grouped = [np.clip(x, 0, 1) for x in _undo_clipping(noisy, grouped, sig_t, clean_sigma=0.0)]
            report(f"{v}+grouped {setting}", grouped, (time.perf_counter() - t) / len(names))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
