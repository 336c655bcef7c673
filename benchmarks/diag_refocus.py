"""What the focal re-estimation (`AlignConfig.refocus_min_change`) costs and buys on the real sets.

Runs `mvgeo align` without the dense stereo (`bench_real.OURS`) with the default threshold (0.1: the
pairs are computed again when the bundle adjustment moves the focal by more than 10 %), with 0.2, and
with the re-estimation off (0), alternating the three twice on the same images: DTU scan24 cluster
(clean and sigma 25/255, noise seeds 0-2), the temple ring (clean) and DTU scan24 spread (clean).
Prints one table row per run: set, variant, registered, rotation error median / max (deg), translation
direction error (deg), ATE / scale, focal error %, seconds, note.

Usage: python benchmarks/diag_refocus.py
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_real as br  # noqa: E402  (its own imports put cv2 before pycolmap)


def main() -> int:
    variants = {"default (0.1)": br.OURS, "0.2": dataclasses.replace(br.OURS, refocus_min_change=0.2),
                "off (0)": dataclasses.replace(br.OURS, refocus_min_change=0.0)}
    sets = [(br.dtu_set("cluster"), [None, 0, 1, 2]), (br.temple_set(), [None]), (br.dtu_set("spread"), [None])]
    work = Path(tempfile.mkdtemp(prefix="diag_refocus_"))
    print("| set | refocus_min_change | registered | rot med | rot max | transl dir | ATE / scale | focal err % | s "
          "| note |\n|---|---|---|---|---|---|---|---|---|---|")
    for s, seeds in sets:
        if s is None:
            continue
        for seed in seeds:
            folder = br.prepare(s, work, noisy=seed is not None, seed=seed or 0)
            label = f"{s.name}, {'clean' if seed is None else f'sigma 25, noise seed {seed}'}"
            for rep in range(2):
                for name in (list(variants) if rep == 0 else list(reversed(variants))):
                    r = br.run_ours(label, name, folder, s.gt, float(s.K[0, 0]), None, variants[name])
                    cells = [f"{x:.4g}" if isinstance(x, float) else str(x) for x in r[:9]] + [str(r[11])[:100]]
                    print("| " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
