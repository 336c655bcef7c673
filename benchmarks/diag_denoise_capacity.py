"""The default denoiser against the UNet's width, batch, patch size and training length, on whole real photos.

Trains the `default` preset's UNet (`denoise.n2v.n2v_preset("default")`: width 16, 4 levels, 8 patches of
64 px per step, lr 1e-3 on a cosine schedule) with one objective on a dataset's noisy training photos, as
the pipeline's denoise stage does (`train_with_method`, then `denoise_with_method` with 8 passes and the
clipped-noise inverse), changing one setting at a time, and scores the photos against `clean/` (PSNR,
SSIM over the whole photos). Made for a GPU, where each run takes 20-80 s; on 2 CPU cores one run of the
default takes about 10 minutes (`benchmarks/diag_objective_photos.py --width/--batch` is the same training
on one configuration, and writes its photos).

Usage: python benchmarks/diag_denoise_capacity.py DATA_ROOT OUT.json [--device cuda] [--runs NAME,...]
       [--time-steps N] [--passes K[,K...]] [--repeat N]
(DATA_ROOT holds the dataset folders named in RUNS, e.g. `runs/real` with `dtu24_cluster12_s25`,
`dtu24_cluster12_pg`, `temple_ring_s25` as imported in docs/bench/pipeline.md; each needs `images/`,
`clean/` and `split.json`; only the training views are read.) Writes OUT.json (device, torch, date, command,
rows) after each run. `--time-steps N` only times N training steps of each run (seconds per step, no
scores): what a setting costs on this device, e.g. `--device cpu --time-steps 30` on the 2-core machine.
`--passes` (default 8, the pipeline's) scores each trained network with each number of inference passes
(recorruptions for R2R; the first is `psnr`/`ssim`, the others `psnr_pK`/`ssim_pK`). `--repeat N` trains
each run N times (rows carry `rep`): on a GPU the same seed does not give the same network, and a rare run
diverges. Each row also records the training loss's maximum and the median of its last 50 steps.
The first run on a GPU includes CUDA's start-up (about 5 s).
"""

import argparse
import datetime
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

#: name -> (dataset folder, objective, width, steps, batch, patch px, seed). The objective is what the
#: `default` preset's "auto" rule picks for the dataset (R2R on DTU, Neighbor2Neighbor on the temple).
RUNS: dict[str, tuple[str, str, int, int, int, int, int]] = {
    "dtu_base": ("dtu24_cluster12_s25", "r2r", 16, 2000, 8, 64, 0),
    "dtu_base_seed1": ("dtu24_cluster12_s25", "r2r", 16, 2000, 8, 64, 1),
    "dtu_w24_b16": ("dtu24_cluster12_s25", "r2r", 24, 2000, 16, 64, 0),
    "dtu_w32": ("dtu24_cluster12_s25", "r2r", 32, 2000, 8, 64, 0),
    "dtu_w32_seed1": ("dtu24_cluster12_s25", "r2r", 32, 2000, 8, 64, 1),
    "dtu_b32": ("dtu24_cluster12_s25", "r2r", 16, 2000, 32, 64, 0),
    "dtu_p128": ("dtu24_cluster12_s25", "r2r", 16, 2000, 8, 128, 0),
    "dtu_w32_b32": ("dtu24_cluster12_s25", "r2r", 32, 2000, 32, 64, 0),
    "dtu_w32_b16_4k": ("dtu24_cluster12_s25", "r2r", 32, 4000, 16, 64, 0),
    "dtu_w48_b16_p128_4k": ("dtu24_cluster12_s25", "r2r", 48, 4000, 16, 128, 0),
    "dtu_w32_1000": ("dtu24_cluster12_s25", "r2r", 32, 1000, 8, 64, 0),
    "dtu_w32_1500": ("dtu24_cluster12_s25", "r2r", 32, 1500, 8, 64, 0),
    "dtu_w32_1000_seed1": ("dtu24_cluster12_s25", "r2r", 32, 1000, 8, 64, 1),
    "dtu_w32_1500_seed1": ("dtu24_cluster12_s25", "r2r", 32, 1500, 8, 64, 1),
    "pg_base": ("dtu24_cluster12_pg", "r2r", 16, 2000, 8, 64, 0),
    "pg_w32_1000": ("dtu24_cluster12_pg", "r2r", 32, 1000, 8, 64, 0),
    "pg_w32_1500": ("dtu24_cluster12_pg", "r2r", 32, 1500, 8, 64, 0),
    "pg_w32": ("dtu24_cluster12_pg", "r2r", 32, 2000, 8, 64, 0),
    "pg_w32_b16_4k": ("dtu24_cluster12_pg", "r2r", 32, 4000, 16, 64, 0),
    "temple_base": ("temple_ring_s25", "neighbor2neighbor", 16, 2000, 8, 64, 0),
    "temple_b32": ("temple_ring_s25", "neighbor2neighbor", 16, 2000, 32, 64, 0),
    "temple_w32_b16": ("temple_ring_s25", "neighbor2neighbor", 32, 2000, 16, 64, 0),
    "temple_w32_b16_4k": ("temple_ring_s25", "neighbor2neighbor", 32, 4000, 16, 64, 0),
}


def _load(folder: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    from mvgeo.common.imageio import read_image

    train = json.loads((folder / "split.json").read_text())["train"]
    noisy = [np.asarray(read_image(folder / "images" / n), dtype=np.float32) for n in train]
    clean = [np.asarray(read_image(folder / "clean" / n), dtype=np.float64) for n in train]
    return noisy, clean


def _scores(photos: list[np.ndarray], clean: list[np.ndarray]) -> tuple[float, float]:
    import torch

    from mvgeo.image_metrics import ssim

    def t(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float64))[None]

    psnr = [-10 * np.log10(np.mean((p.astype(np.float64) - c) ** 2)) for p, c in zip(photos, clean, strict=True)]
    return float(np.mean(psnr)), float(np.mean([float(ssim(t(p), t(c))) for p, c in zip(photos, clean, strict=True)]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_root", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--runs", default=",".join(RUNS), help="comma-separated names of RUNS")
    ap.add_argument("--time-steps", type=int, default=0, help="only time this many training steps per run")
    ap.add_argument("--passes", default="8", help="inference passes to score, comma-separated (default 8)")
    ap.add_argument("--repeat", type=int, default=1, help="train each run this many times (default 1)")
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    try:
        passes = [int(k) for k in args.passes.split(",")]
    except ValueError:
        passes = []
    if not passes or min(passes) < 1:
        ap.error(f"--passes: positive integers, comma-separated (got {args.passes!r})")
    names = [n for n in args.runs.split(",") if n]
    unknown = [n for n in names if n not in RUNS]
    if not names or unknown or len(set(names)) != len(names):
        ap.error(f"--runs: names of RUNS, each once (got {args.runs!r}); known: {', '.join(RUNS)}")
    if args.time_steps < 0:
        ap.error("--time-steps must be >= 0")
    if not args.out.parent.is_dir():
        ap.error(f"no folder {args.out.parent} for {args.out.name}")
    missing = sorted({RUNS[n][0] for n in names if not (args.data_root / RUNS[n][0] / "split.json").is_file()})
    if missing:
        ap.error(f"no dataset {missing} under {args.data_root} (import them as docs/bench/pipeline.md shows)")

    import torch

    from denoise.n2v import n2v_preset
    from denoise.self_supervised import denoise_with_method, train_with_method

    if args.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error(f"--device {args.device}: torch sees no CUDA device")
    device_name = torch.cuda.get_device_name(args.device) if args.device.startswith("cuda") else "cpu"
    record = {"device": device_name, "torch": torch.__version__,
              "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
              "command": " ".join(["python", *sys.argv]), "rows": []}
    cache = {}
    for name, rep in [(n, r) for n in names for r in range(args.repeat)]:
        folder, method, width, steps, batch, patch, seed = RUNS[name]
        if folder not in cache:
            cache[folder] = _load(args.data_root / folder)
        noisy, clean = cache[folder]
        base = n2v_preset("default", steps=args.time_steps or steps)
        cfg = replace(base, method=method, unet=replace(base.unet, width=width), batch_size=batch, patch_px=patch)
        t0 = time.perf_counter()
        model = train_with_method(noisy, cfg, seed=seed, device=args.device)
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        train_s = time.perf_counter() - t0
        row = dict(name=name, dataset=folder, method=method, width=width, steps=steps, batch=batch, patch=patch,
                   seed=seed, **({"rep": rep} if args.repeat > 1 else {}))
        loss = np.asarray(model.history, np.float64)
        if len(loss):
            row.update(loss_max=round(float(loss.max()), 4), loss_last50=round(float(np.median(loss[-50:])), 4))
        if model.restarts:  # the divergence guard restarted the training (its losses: the last run's)
            row["restarts"] = [r.to_json() for r in model.restarts]
        if args.time_steps:
            row["s_per_step"] = round(train_s / args.time_steps, 4)
        else:
            for k, n_passes in enumerate(passes):
                psnr, ssim = _scores(denoise_with_method(model, noisy, cfg, passes=n_passes, seed=seed), clean)
                tag = "" if k == 0 else f"_p{n_passes}"
                row.update({f"psnr{tag}": round(psnr, 3), f"ssim{tag}": round(ssim, 4)})
            row.update(passes=passes[0], train_s=round(train_s, 1))
        print(row, flush=True)
        record["rows"].append(row)
        args.out.write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
