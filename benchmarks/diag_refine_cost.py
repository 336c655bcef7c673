"""Round 2's refine step on a finished pipeline run: seconds and guard decision with the current code.

Loads round 1's network, the noisy photos of the views round 2 selected and round 1's renders of them,
runs `denoise.round2.refine_round2` (trust target, fine-tuning, blind-spot guard) with the run's
settings and seed, then the K-pass inference of the refine stage, and scores the denoised views
against the clean photos. Run it from two checkouts on the same run folder to compare code versions
(the numbers in docs/bench/pipeline_speed.md came from this script).

Usage:
    .venv/bin/python benchmarks/diag_refine_cost.py RUN CLEAN_DIR
(RUN: a pipeline folder such as OUT/runs/llff_like/seed0/n2v_fused; CLEAN_DIR: the scene's clean/)
"""

import json  # noqa: I001  (eval.cli sets the thread policy before torch loads)
import sys
import time
from pathlib import Path

import eval.cli  # noqa: F401
import numpy as np

from denoise.inference import denoise_images
from denoise.model import load_checkpoint
from denoise.round2 import Round2Config, refine_round2
from eval.pipeline.summaries import SelectionFile
from eval.pipeline.views import read_views


def main(run: Path, clean_dir: Path) -> dict:
    record = json.loads((run / "round2" / "stages" / "refine.json").read_text())
    names = SelectionFile.read(run / "round2" / "selection.json").names
    noisy = list(read_views(run / "inputs", names).values())
    renders = list(read_views(run / "round1" / "renders", names).values())
    clean = list(read_views(clean_dir, names).values())
    model = load_checkpoint(run / "round1" / "n2v_model.pt", device="cpu")
    settings = record["settings"]["round2"]
    known = Round2Config.__dataclass_fields__
    cfg = Round2Config(**{k: v for k, v in settings.items() if k in known})
    t0 = time.perf_counter()
    out, rep = refine_round2(model, noisy, renders, cfg, seed=record["seed"])
    refine_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    den = denoise_images(out, noisy, passes=record["settings"]["passes"], seed=0, fuse=True)
    infer_s = time.perf_counter() - t0
    psnr = float(np.mean([10 * np.log10(1.0 / np.mean((np.clip(d, 0, 1) - c) ** 2))
                          for d, c in zip(den, clean, strict=True)]))
    return {"views": len(names), "refine_s": round(refine_s, 1), "inference_s": round(infer_s, 1),
            "loss_before": rep.loss_before, "loss_after": rep.loss_after, "reverted": rep.reverted,
            "denoised_psnr_db": round(psnr, 3)}


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]), Path(sys.argv[2]))))
