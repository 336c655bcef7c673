"""Round 1's denoise stage (the `default` preset's) on a dataset's training photos at a pixel-shuffle stride.

Writes OUT/denoised/ (score it with `benchmarks/diag_photo_scores.py DATASET/clean OUT/denoised`) and prints
the stage's time, the stride it ran at and, for stride 0, the noise levels by stride that chose it
(`denoise.pixel_shuffle.choose_stride`). The photos are those of the dataset's split.json `train` list.

Usage: .venv/bin/python benchmarks/diag_pd_denoise.py DATASET STRIDE OUT
(DATASET: a `denoise-gs dataset import` folder; STRIDE: 0 = measured, 1 = off, 2-4)
"""
import argparse
import dataclasses
import json
import time
from pathlib import Path

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads
from eval.pipeline import preset
from eval.pipeline.stage import StageContext
from eval.pipeline.stage_settings import round_settings
from eval.pipeline.stages import denoise
from eval.pipeline.summaries import DenoiseSummary
from eval.pipeline.views import read_views, write_views


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("stride", type=int, choices=range(0, 5))
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    train = {Path(n).stem for n in json.loads((args.dataset / "split.json").read_text())["train"]}
    args.out.mkdir(parents=True)
    write_views(args.out / "noisy", {k: v for k, v in read_views(args.dataset / "images").items() if k in train})
    settings = dataclasses.replace(round_settings(preset("default"), 1).denoise, pd_stride=args.stride)
    t = time.perf_counter()
    summary = DenoiseSummary.from_json(denoise(StageContext(
        name="denoise", work_dir=args.out, inputs={"noisy": args.out / "noisy"}, settings=settings, seed=0)))
    print(json.dumps({"stride": summary.pd_stride, "noise_level_by_stride_255": summary.noise_level_by_stride_255,
                      "objective": summary.objective, "seconds": round(time.perf_counter() - t, 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
