"""The synthetic object_ring orbit at 256x192 under dithers: registered right, or refused with a named reason?

The ring is `data_synth`'s object_ring rendered with `--views` views (24: 21 training views, 30 deg gaps at the
held-out ones; 32: 28 training views), re-quantised with a dither of 0.5/255 (`diag_located_groups.
dithered_copies`, dither seeds 0..`--dithers`-1), aligned with the benchmark config (`bench_real.OURS`). A row per
dither: registered views, rotation error median and max over all pairs of registered views, the worst view
(the median of its pairs' errors), ATE over scene scale, seconds, the candidates' starts, the refusal.

Usage: .venv/bin/python benchmarks/diag_ring_dithers.py [--views=24] [--dithers=6] [--out=NAME]
(writes docs/bench/NAME.md)
"""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from _common import cli_option, md_table, write_fragment
from diag_located_groups import align_row, candidate_starts, dithered_copies, machine_line

from mvgeo.common.imageio import list_images
from mvgeo.sparse_model import read_sparse_model


def main() -> int:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return 0
    views = int(cli_option("views", "24"))
    dithers = int(cli_option("dithers", "6"))
    out = cli_option("out", f"ring{views}_dithers")
    from data_synth import render_scene

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        d = render_scene("object_ring", work / "ring", size_wh=(256, 192), views=views)
        train = json.loads((d / "split.json").read_text())["train"]
        gt = read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()
        paths = [p for p in list_images(d / "images") if p.name in train]
        for seed in range(dithers):
            rows.append(align_row(f"object_ring, {len(train)} of {views} views", str(seed),
                                  dithered_copies(paths, work / f"dither{seed}", seed), gt, candidate_starts))
            print(rows[-1], file=sys.stderr, flush=True)
    body = machine_line() + md_table(["set", "dither seed", "registered", "rot med (deg)", "rot max (deg)",
                                      "worst view (deg)", "ATE / scale", "time (s)", "candidates' starts",
                                      "refused"], rows) + "\n"
    print(write_fragment(out, f"object_ring ({views} views) under dithers", body,
                         f"`python benchmarks/diag_ring_dithers.py --views={views} --dithers={dithers} --out={out}`"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
