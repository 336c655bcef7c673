"""Round 2's guard on finished pipeline runs: the round-1 and the fine-tuned (round-2) networks scored again by
the blind-spot loss on the views round 2 selected, per view and grid cell, and the paired decision
(`denoise.round2.guard_decision`) at several `guard_z`. Shows whether a recorded gain was more than noise.

Usage: .venv/bin/python benchmarks/diag_round2_guard.py RUN [RUN ...] [--seed S]
(RUN: a pipeline output folder whose round2/ holds `n2v_model.pt` and `selection.json`; the noisy photos are
read from RUN/inputs). `--seed` draws the masked pixels' replacements (the guard itself uses the run's seed
+ 1). Prints the recorded decision, the recomputed losses, the decision for z = 0, 1, 2, 3 and the gain per
view.
"""
import argparse
import json
from pathlib import Path

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads


def main() -> None:
    import numpy as np
    import torch

    from denoise.model import load_checkpoint
    from denoise.round2 import blind_spot_blocks, guard_decision, spread_cells
    from eval.pipeline.summaries import RefineSummary, SelectionFile
    from eval.pipeline.views import read_views

    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cells", type=int, default=5)
    args = ap.parse_args()
    for run in args.runs:
        names = SelectionFile.read(run / "round2" / "selection.json").names
        noisy = read_views(run / "inputs", names)
        ys = [torch.from_numpy(np.ascontiguousarray(v.transpose(2, 0, 1))) for v in noisy.values()]
        before_model = load_checkpoint(run / "round1" / "n2v_model.pt")
        after_model = load_checkpoint(run / "round2" / "n2v_model.pt")
        record = json.loads((run / "round2" / "stages" / "refine.json").read_text())
        r2 = RefineSummary.from_json(record.get("summary") or {}).round2_report()
        print(run, "recorded:", None if r2 is None else {"loss_before": r2.loss_before, "loss_after": r2.loss_after,
                                                         "loss_gain_se": r2.loss_gain_se, "reverted": r2.reverted})
        cells = spread_cells(args.cells)
        before = blind_spot_blocks(before_model, ys, seed=args.seed, cells=cells)[0]
        after = blind_spot_blocks(after_model, ys, seed=args.seed, cells=cells)[0]
        for z in (0.0, 1.0, 2.0, 3.0):
            keep, gain, se = guard_decision(before, after, z)
            print(f"  z {z}: keep {keep}, gain {gain:.3g}, standard error {se:.3g}")
        print("  gain per view:", np.array2string((before - after).mean(axis=1), precision=6))


if __name__ == "__main__":
    main()
