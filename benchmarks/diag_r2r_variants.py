"""R2R's recorruption scale and decoder dropout, measured on an evaluation's noisy training photos.

Trains the `default` preset's denoiser (R2R, width 16, 2000 steps unless `--steps`) on the noisy photos
of one evaluation run and scores the denoised photos (8 recorrupted passes, the clipped-noise inverse, as
the denoise stage runs them) against the dataset's clean photos, once per variant:

- `alpha=A`: `N2VConfig.r2r_alpha` (input ``y + A z``, target ``y - z / A``; the preset's 0.5);
- `dropout=P`: element-wise dropout of probability P before every decoder block (Self2Self's remedy for a
  network that memorises the noise of the few photos it trains on), off at inference, and averaged over
  the 8 passes with it on (`mc`).

Usage: .venv/bin/python benchmarks/diag_r2r_variants.py RUN_DIR DATASET [--steps N] VARIANT...
(RUN_DIR: an evaluation's `runs/SCENE/seedK/product` folder, whose `inputs/` are the noisy training photos;
DATASET: the dataset folder with `clean/`.) Prints one line per variant: PSNR of the photos, training s.
"""
import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

# isort: off
import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
import torch
import torch.nn as nn
import torch.nn.functional as F
# isort: on

import denoise.unet as unet_module
from denoise.parallel import one_thread_per_task
from denoise.self_supervised import denoise_with_method, r2r_noise_std, train_with_method
from eval.pipeline.config import preset
from eval.pipeline.stage_settings import n2v_config
from mvgeo.common.imageio import read_image


class _Dropout(nn.Module):
    """Dropout that stays on in eval mode while `_Dropout.always` is set (Monte-Carlo inference)."""

    always = False

    def __init__(self, p: float):
        super().__init__()
        self.p = p

    def forward(self, x):
        return F.dropout(x, self.p, training=self.training or _Dropout.always)


def _with_decoder_dropout(p: float):
    """Patch `UNet.__init__` so that every decoder block is preceded by `_Dropout(p)` (this script only)."""
    original = unet_module.UNet.__init__

    def init(self, config=None):
        original(self, config)
        for k, block in enumerate(self.decoders):
            self.decoders[k] = nn.Sequential(_Dropout(p), block)

    unet_module.UNet.__init__ = init
    return original


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.asarray(a, np.float64) - b) ** 2)))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("variants", nargs="+", help="alpha=A or dropout=P")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    names = sorted(p.name for p in (args.run_dir / "inputs").iterdir() if p.suffix == ".png")
    noisy = [read_image(args.run_dir / "inputs" / n) for n in names]
    clean = [read_image(args.dataset / "clean" / n) for n in names]
    stds = [r2r_noise_std(im) for im in noisy]
    base = n2v_config(preset("default").denoise)
    if args.steps is not None:
        base = dataclasses.replace(base, steps=args.steps)
    for spec in args.variants:
        key, _, value = spec.partition("=")
        cfg, original, runs = base, None, [("", False)]
        if key == "alpha":
            cfg = dataclasses.replace(base, r2r_alpha=float(value))
        elif key == "dropout":
            original = _with_decoder_dropout(float(value))
            runs = [("", False), (" mc", True)]
        else:
            print(f"unknown variant {spec!r}", file=sys.stderr)
            return 2
        torch.manual_seed(args.seed)  # the dropout masks' stream
        t = time.perf_counter()
        with one_thread_per_task():
            model = train_with_method(noisy, cfg, seed=args.seed, device="cpu", noise_sigma=stds)
            seconds = time.perf_counter() - t
            for label, mc in runs:
                _Dropout.always = mc
                out = denoise_with_method(model, noisy, cfg, passes=8, seed=args.seed, noise_sigma=stds)
                score = np.mean([_psnr(a, b) for a, b in zip(out, clean, strict=True)])
                print(f"{spec}{label} steps={cfg.steps}: {score:.3f} dB, training {seconds:.0f} s", flush=True)
        _Dropout.always = False
        if original is not None:
            unet_module.UNet.__init__ = original
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
