"""CAREamics N2V2 on given noisy images: the external peer of `bench_denoise.py careamics`.

Runs in the separate CAREamics environment (`bash tools/setup_careamics.sh` makes `.venv-careamics`;
careamics 0.3.5 pins torch < 2.14 and numpy <= 2.4.6, which the project's environment does not allow), so
it imports nothing from the project. `bench_denoise.py careamics` writes the noisy images to an .npz, runs
this script with that environment's Python and reads the result back.

Usage: `.venv-careamics/bin/python benchmarks/careamics_peer.py IN.npz OUT.npz --steps 400 --batch 8
--patch 64 --seed 0 --threads 2` (IN.npz: `noisy`, (S, Y, X, C) float32 in [0, 1]). OUT.npz: `denoised`
(same shape), `train_s`, `predict_s`, `n_params`, `versions`.

Training: `careamics.config.create_n2v_config(use_n2v2=True)` (CAREamics' N2V2: blur-pool UNet without
the top skip, median replacement; its default UNet, optimiser and schedule), patches of `--patch` px, batches of
`--batch`, `--steps` optimiser steps in all (Lightning's `max_steps`; checked), the library's default flips and
rotations, its default 8 validation patches taken from the same images. Prediction: the whole images, no
tiling (they are small).
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("inp")
    ap.add_argument("out")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--patch", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    import careamics
    import lightning
    import torch
    from careamics import CAREamist
    from careamics.config import create_n2v_config

    torch.set_num_threads(args.threads)
    lightning.seed_everything(args.seed, verbose=False)
    noisy = np.load(args.inp)["noisy"].astype(np.float32)
    # An epoch is one pass over the images' patches (about 13 batches here), and `num_steps` only caps it:
    # Lightning's `max_steps` sets the budget, with as many epochs as that takes.
    config = create_n2v_config(experiment_name="peer", data_type="array", axes="SYXC",
                               patch_size=[args.patch, args.patch], batch_size=args.batch, num_epochs=100_000,
                               use_n2v2=True, n_channels=noisy.shape[-1])
    config.training_config.trainer_params["max_steps"] = args.steps
    with tempfile.TemporaryDirectory() as work:
        model = CAREamist(config, work_dir=work, enable_progress_bar=False)
        t = time.perf_counter()
        model.train(train_data=noisy)
        train_s = time.perf_counter() - t
        t = time.perf_counter()
        pred, _ = model.predict(noisy, data_type="array", axes="SYXC")
        predict_s = time.perf_counter() - t
        n_params = sum(p.numel() for p in model.model.parameters())
        steps_done = int(model.trainer.global_step)
    if steps_done != args.steps:
        raise SystemExit(f"trained {steps_done} steps, not the {args.steps} asked for")
    denoised = np.concatenate([np.asarray(p, np.float32).reshape(-1, *noisy.shape[1:]) for p in pred])
    np.savez(args.out, denoised=denoised, train_s=train_s, predict_s=predict_s, n_params=n_params,
             versions=f"careamics {careamics.__version__}, torch {torch.__version__}")


if __name__ == "__main__":
    main()
