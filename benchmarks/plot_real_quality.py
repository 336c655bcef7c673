"""One figure of the held-out quality on real photos: per set, the noisy-photo splat (b), the product, the
product with the true cameras, the clean photos with their own cameras (a perfect denoiser through the same
front end) and with the true cameras, PSNR and LPIPS, mean and sample std over seeds.

Each set is given as `LABEL=RESULTS[,RESULTS...]`: `results.json` files of `denoise-gs eval` runs on that set,
whose rows are pooled (one evaluation may hold the product, another the baselines); a method missing from a
set is left out of its group. `RESULTS#method[+method...]` takes only those methods' rows from that file (e.g. the
product of an evaluation whose references ran at another splat length). A dashed mark shows (b) + 3 dB, issue
23's goal for the product.

Usage: .venv/bin/python benchmarks/plot_real_quality.py OUT.png "LABEL=runs/a/results.json,runs/b/results.json" ...
"""
import argparse
import json
import sys
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

METHODS = {"instantsplat": "(b) splat of the noisy photos", "product": "product (own cameras)",
           "product@gt_poses": "product, true cameras", "oracle_clean": "clean photos (own cameras)",
           "oracle_clean@gt_poses": "clean photos, true cameras"}
COLOURS = {"instantsplat": "#9e9e9e", "product": "#1f77b4", "product@gt_poses": "#7fb2e5", "oracle_clean": "#98df8a",
           "oracle_clean@gt_poses": "#2ca02c"}


def _pooled(files: list[str]) -> dict[str, dict[str, list[float]]]:
    """method -> metric -> values over seeds (failed runs left out); `FILE#m1+m2` keeps only those methods."""
    out: dict[str, dict[str, list[float]]] = {}
    seen: set[tuple[str, int]] = set()
    for spec in files:
        f, _, only = spec.partition("#")
        keep = set(only.split("+")) & set(METHODS) if only else set(METHODS)
        for r in json.loads(Path(f).read_text())["runs"]:
            key = (r["method"], r["seed"])
            if r["method"] not in keep or key in seen or r.get("error") or r["psnr_db"] is None:
                continue
            seen.add(key)
            for m in ("psnr_db", "lpips"):
                out.setdefault(r["method"], {}).setdefault(m, []).append(float(r[m]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("sets", nargs="+", help="LABEL=results.json[,results.json...]")
    args = ap.parse_args()
    sets = []
    for spec in args.sets:
        label, _, files = spec.partition("=")
        if not files:
            print(f"{spec!r}: expected LABEL=results.json[,...]", file=sys.stderr)
            return 2
        sets.append((label, _pooled(files.split(","))))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.4))
    width = 0.8 / len(METHODS)
    for ax, metric, label in ((axes[0], "psnr_db", "held-out PSNR (dB), higher is better"),
                              (axes[1], "lpips", "held-out LPIPS, lower is better")):
        for k, method in enumerate(METHODS):
            xs, means, stds = [], [], []
            for i, (_, data) in enumerate(sets):
                v = data.get(method, {}).get(metric)
                if v:
                    xs.append(i + (k - (len(METHODS) - 1) / 2) * width)
                    means.append(np.mean(v))
                    stds.append(np.std(v, ddof=1) if len(v) > 1 else 0.0)
            if xs:
                ax.bar(xs, means, width, yerr=stds, color=COLOURS[method], label=METHODS[method], capsize=2)
                for x, m, sd in zip(xs, means, stds, strict=True):
                    ax.text(x, m + sd, f"{m:.2f}" if metric == "psnr_db" else f"{m:.3f}", ha="center",
                            va="bottom", fontsize=6)
        if metric == "psnr_db":
            for i, (_, data) in enumerate(sets):
                b = data.get("instantsplat", {}).get("psnr_db")
                if b:
                    ax.hlines(np.mean(b) + 3.0, i - 0.4, i + 0.4, colors="k", linestyles="dashed", linewidth=1,
                              label="(b) + 3 dB (goal)" if i == 0 else None)
            lo = min(min(np.mean(v["psnr_db"]) for v in d.values()) for _, d in sets)
            ax.set_ylim(np.floor(lo) - 1.0, ax.get_ylim()[1] + 0.3)
        ax.set_xticks(range(len(sets)), [s for s, _ in sets], fontsize=8)
        ax.set_title(label, fontsize=9)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="upper center", ncols=len(labels), frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
