"""Coarse-to-fine splat training against full resolution: train time, held-out PSNR, sub-step profile.

`llff_like_clean` (data_synth built-in scene) at `--size` (default its native 504x378), the scene's
training split (17 views) with ground-truth poses (`optimize_poses=False`, so that held-out views can be
rendered at their true poses), the `instantsplat` preset's 1000 iterations, initial points back-projected
from the ground-truth depth every `8 * W / 504` px (~50k Gaussians at either size). Schedules
(`--configs`, comma-separated): `full` (no coarse phase) and `S:F` = `coarse_scale` S for the first F of
the iterations, e.g. `0.5:0.5`; `S:F:LOWPASS` also sets the coarse steps' low-pass (`LOWPASS`).

All schedules run in one process, back to back, and `--repeat=2` runs them a second time in reverse
order, so that a change of the machine's load hits them alike; train seconds are per run, the
sub-step split (`TrainResult.timings_s["optimize/..."]`) is from the first run of each schedule.
Training is deterministic on CPU, so the repeat's PSNR is identical and only its time is new. The
first run of each schedule also records the held-out PSNR after `CURVE_STEPS` steps (early stopping
within the same learning-rate schedule); those renders are timed apart and left out of train seconds.

Held-out PSNR: mean over the scene's test views of the per-image PSNR of the render against the clean
image (`clean/`); training PSNR likewise over the training views (all at full size).

Each invocation is a batch; batches accumulate per size in docs/bench/splat_schedule.json and
docs/bench/splat_schedule.md is rebuilt from all of them (speed-ups compare runs within one batch only).
Options: `--size=WxH`, `--iters=N`, `--configs=...`, `--repeat=N`.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from _common import ROOT, cli_option, md_table, write_fragment  # noqa: E402

from data_synth import render_scene  # noqa: E402
from mvgeo.common.imageio import read_image  # noqa: E402
from splat.dataset import load_views, points_from_depth  # noqa: E402
from splat.rasterize import RasterConfig  # noqa: E402
from splat.render import render_views  # noqa: E402
from splat.train import OPTIMIZE_SUBSTEPS, preset, train_gaussians  # noqa: E402

KERNEL_THREADS = 2
#: Low-pass of the coarse steps (third field of a schedule): "" keeps the full-size `RasterConfig`
#: (eps2d 0.3 coarse px^2); "area" sets eps2d to the full-size low-pass in coarse px^2 plus the area
#: filter's variance (0.3 s^2 + 1/12); "area-aa" also turns on the opacity compensation (Mip-Splatting).
LOWPASS = ("", "area", "area-aa")
#: Steps after which the held-out PSNR is recorded (the first run of each schedule): what stopping early
#: within the same learning-rate schedule would give.
CURVE_STEPS = (250, 500, 700, 800, 900)
#: The quality budget of the speed work (issue goal): held-out PSNR within this of the full-size schedule.
QUALITY_TOL_DB = 0.1
RESULTS = ROOT / "docs" / "bench" / "splat_schedule.json"


def _load() -> str:
    return " / ".join(f"{x:.1f}" for x in os.getloadavg())


def _parse_config(text: str) -> tuple[str, float, float, str]:
    if text == "full":
        return "full", 1.0, 0.0, ""
    parts = text.split(":")
    scale, fraction = float(parts[0]), float(parts[1])
    lowpass = parts[2] if len(parts) > 2 else ""
    if lowpass not in LOWPASS:
        raise SystemExit(f"unknown low-pass {lowpass!r} in {text!r}; use one of {sorted(LOWPASS)}")
    return f"{scale:g} for {100 * fraction:.0f}%" + (f", {lowpass}" if lowpass else ""), scale, fraction, lowpass


def _coarse_raster(raster: RasterConfig, scale: float, lowpass: str) -> RasterConfig | None:
    """None (the full-size options) or the coarse steps' options for a `LOWPASS` name."""
    if not lowpass:
        return None
    # The full-size low-pass in coarse px^2 plus the variance of the area filter over one coarse pixel.
    eps = raster.eps2d * scale**2 + 1.0 / 12.0
    return replace(raster, eps2d=eps, antialiased=lowpass == "area-aa")


def _mean_psnr(model, views, clean) -> float:
    outs = render_views(model, views.cameras, views.cam_from_world)
    return float(np.mean([-10 * np.log10(np.mean((o - c) ** 2)) for o, c in zip(outs, clean, strict=True)]))


def measure(size_wh: tuple[int, int], iters: int, configs: list[str], repeat: int, save=None) -> dict:
    """Train every schedule `repeat` times; `save(result_so_far)` after each run (partial results survive)."""
    load0 = _load()
    started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "llff"
        render_scene("llff_like_clean", data, size_wh=size_wh)
        train = load_views(data, split="train")
        test = load_views(data, split="test")
        stride = max(1, round(8 * size_wh[0] / 504))
        xyz, rgb = points_from_depth(data, train, stride_px=stride)
        clean_train = [read_image(data / "clean" / n) for n in train.names]
        clean_test = [read_image(data / "clean" / n) for n in test.names]
    # Warm-up outside the timings: kernel loading and first-touch allocations.
    train_gaussians(train.images[:2], train.cameras[:2], train.cam_from_world[:2], xyz[:1000], rgb[:1000],
                    preset("instantsplat", iters=2, optimize_poses=False))
    parsed = [_parse_config(c) for c in configs]

    def summary():
        return _summary(size_wh, iters, train, test, xyz, stride, load0, started, runs)

    order = list(range(len(parsed)))
    runs: dict[str, dict] = {}
    for rep in range(repeat):
        for k in (order if rep % 2 == 0 else order[::-1]):
            label, scale, fraction, lowpass = parsed[k]
            cfg = preset("instantsplat", iters=iters, optimize_poses=False, coarse_scale=scale,
                         coarse_fraction=fraction)
            cfg = replace(cfg, raster=replace(cfg.raster, num_threads=KERNEL_THREADS))
            cfg = replace(cfg, coarse_raster=_coarse_raster(cfg.raster, scale, lowpass))
            curve: dict[int, float] = {}

            def on_step(step, model, curve=curve):
                if step in CURVE_STEPS and step < iters:
                    curve[step] = round(_mean_psnr(model, test, clean_test), 3)

            t0 = time.perf_counter()
            res = train_gaussians(train.images, train.cameras, train.cam_from_world, xyz, rgb, cfg,
                                  on_step=on_step if rep == 0 else None)
            # The held-out curve's renders are timed apart ("optimize/callback") and left out here.
            elapsed = time.perf_counter() - t0 - res.timings_s.get("optimize/callback", 0.0)
            entry = runs.setdefault(label, {"train_s": [], "config": configs[k]})
            entry["train_s"].append(round(elapsed, 1))
            if rep == 0:
                entry["heldout_curve_db"] = curve
                entry["timings_s"] = res.timings_s
                entry["heldout_psnr_db"] = round(_mean_psnr(res.model, test, clean_test), 3)
                entry["train_psnr_db"] = round(_mean_psnr(res.model, train, clean_train), 3)
                entry["num_gaussians"] = res.model.num_gaussians
            print(f"[{rep}] {label}: {elapsed:.1f} s, held-out {entry['heldout_psnr_db']:.3f} dB, "
                  f"load {_load()}", flush=True)
            if save is not None:
                save(summary())
    return summary()


def _summary(size_wh, iters, train, test, xyz, stride, load0, started, runs) -> dict:
    return {"size": f"{size_wh[0]}x{size_wh[1]}", "started": started, "iters": iters, "train_views": len(train.names),
            "test_views": len(test.names), "init_points": int(len(xyz)), "stride_px": stride,
            "load_start": load0, "load_end": _load(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "runs": runs}


def _section(res: dict) -> str:
    runs = res["runs"]
    full = runs.get("full")
    rows, prof = [], []
    for label, r in runs.items():
        mean_s = float(np.mean(r["train_s"]))
        speed = f"{float(np.mean(full['train_s'])) / mean_s:.2f}x" if full else "-"
        dpsnr = f"{r['heldout_psnr_db'] - full['heldout_psnr_db']:+.3f}" if full else "-"
        rows.append([label, " / ".join(f"{t:.1f}" for t in r["train_s"]), speed, f"{r['heldout_psnr_db']:.3f}",
                     dpsnr, f"{r['train_psnr_db']:.3f}"])
        t = r["timings_s"]
        prof.append([label, f"{t['optimize']:.1f}"] + [f"{t.get(f'optimize/{k}', float('nan')):.1f}"
                                                        for k in OPTIMIZE_SUBSTEPS] + [f"{t['setup']:.1f}"])
    verdict = ""
    if full:
        ok = [f"{label} ({float(np.mean(full['train_s'])) / float(np.mean(r['train_s'])):.2f}x)"
              for label, r in runs.items() if label != "full"
              and r["heldout_psnr_db"] >= full["heldout_psnr_db"] - QUALITY_TOL_DB]
        verdict = (f"\nWithin {QUALITY_TOL_DB} dB of the full-size schedule on the held-out views: "
                   f"{', '.join(ok) if ok else 'none of the coarse schedules'}.\n")
    else:
        verdict = ("\nNo full-size run in this batch: compare the PSNR with another batch of the same size "
                   "(same scene, points and seed; the C++ kernels may have changed between batches).\n")
    steps = sorted({int(s) for r in runs.values() for s in r.get("heldout_curve_db", {})})
    curve_rows = [[label] + [f"{r['heldout_curve_db'].get(st, r['heldout_curve_db'].get(str(st), float('nan'))):.3f}"
                             for st in steps] + [f"{r['heldout_psnr_db']:.3f}"] for label, r in runs.items()]
    text = (f"### {res['size']}, {res['train_views']} training views, {res['iters']} iterations "
            f"(batch started {res.get('started', res['date'])})\n\n"
            f"{res['init_points']} initial Gaussians (depth every {res['stride_px']} px), "
            f"{res['test_views']} held-out views. Load average (1/5/15 min) {res['load_start']} at the start, "
            f"{res['load_end']} at the end; {res['date']}.\n\n"
            + md_table(["schedule", "train s (each run)", "speed-up", "held-out PSNR dB", "vs full dB",
                        "train-view PSNR dB"], rows) + verdict
            + "\nSeconds per sub-step of the optimisation loop, first run of each schedule "
            "(`TrainResult.timings_s`):\n\n"
            + md_table(["schedule", "optimize"] + list(OPTIMIZE_SUBSTEPS) + ["setup"], prof)
            + "\nHeld-out PSNR (dB) after a number of steps of the same run (stopping early without "
            "shortening the learning-rate schedule):\n\n"
            + md_table(["schedule"] + [str(st) for st in steps] + [str(res["iters"])], curve_rows))
    return text


def main(argv: list[str]) -> int:
    w, h = (int(x) for x in cli_option("size", "504x378").split("x"))
    iters = int(cli_option("iters", "1000"))
    configs = cli_option("configs", "full,0.5:0.5,0.5:0.7").split(",")
    repeat = int(cli_option("repeat", "1"))
    measure((w, h), iters, configs, repeat, save=_save)
    print(_write_markdown().read_text())
    return 0


def _batches(stored: dict, size: str) -> list[dict]:
    entry = stored.get(size, [])
    return [entry] if isinstance(entry, dict) else list(entry)


def _save(res: dict) -> None:
    """Store one invocation's results (a batch) next to the earlier batches of the same size."""
    stored = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    keep = [b for b in _batches(stored, res["size"]) if b.get("started") != res["started"]]
    stored[res["size"]] = keep + [res]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(stored, indent=1))
    _write_markdown()


def _write_markdown() -> Path:
    stored = json.loads(RESULTS.read_text())
    body = (
        "Coarse-to-fine training (`TrainConfig.coarse_scale`, `coarse_fraction`) against the full-size "
        "schedule: `llff_like_clean`, ground-truth poses, the `instantsplat` preset with "
        "`optimize_poses=False`; schedule `S for F%` renders the first F% of the iterations at scale S "
        "(intrinsics rescaled, targets area-averaged). Machine: 2 cores shared with other jobs, run under "
        f"`nice`; torch single-threaded in the trainer, C++ kernels {KERNEL_THREADS} threads. All schedules "
        "of one size ran back to back in one process (benchmarks/bench_splat_schedule.py); with the machine "
        "loaded the seconds are upper bounds, compare the ratios within one table.\n\n"
        + "\n".join(_section(b) for k in sorted(stored, key=lambda s: int(s.split("x")[0]))
                     for b in _batches(stored, k)))
    return write_fragment("splat_schedule", "Splat coarse-to-fine schedule (splat_schedule)", body)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
