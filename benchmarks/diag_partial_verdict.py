"""Does any statistic of the chosen solution tell `--allow-partial`'s wrong models from its right ones?

`mvgeo align --allow-partial` registers the largest group of views it can connect and verify. On the view sets
of `diag_real_subsets.py` it returned models with views more than 5 deg off on four sets (the noisy temple's
16 views, two noisy 12-view arcs, the clean every-other-view set), where the verdict found every kept pair
explained. This script runs every set of `diag_real_subsets.py` (clean and sigma 25/255, EXIF focal) with
`--allow-partial` and with the defaults, and tabulates, for the chosen candidate, what the verdict could look
at besides the pairs it explains:

- `views`, `pairs`: registered views and the verified pairs among them (the candidate's pair geometries);
  `redundancy` = (pairs - (views - 1)) / views, 0 for a tree;
- `in loops of 3`: views that belong to a loop of three verified pairs; `loop core max`: the largest relative
  rotation error among the views of the largest group connected by pairs that lie on such loops;
- `tracks in 3+`: the fraction of the bundle adjustment's tracks observed in at least three views, and the
  fewest such observations of any view;
- `pair rot dev`: median and max over the pairs of the deviation between the result's relative rotation and
  the pair's own (`PairCheck.rotation_deviation_deg`);
- `refocused`: focal re-estimations of the chosen candidate's pairs; `f / prior`: its adjusted focal over the
  EXIF focal the pairs started at.

The chosen candidate is observed by wrapping `mvgeo.align.api.choose_solution` (the script only reads it).

Run: `.venv/bin/python benchmarks/diag_partial_verdict.py [--draws=6] [--out=partial_verdict]` (writes
docs/bench/NAME.md).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import bench_real as br
import diag_real_subsets as drs
import numpy as np
from _common import cli_option, md_table, write_fragment

import mvgeo.align.api as api
from mvgeo.align.graph import components
from mvgeo.common.imageio import list_images
from mvgeo.metrics import compare_poses


def _statistics(c, est: dict, gt: dict) -> list:
    n = len(c.inputs)
    edges = {(min(g.i, g.j), max(g.i, g.j)) for g in c.pairs.geometries}
    adj: dict[int, set[int]] = {v: set() for v in range(n)}
    for a, b in edges:
        adj[a].add(b)
        adj[b].add(a)
    looped = [(a, b) for a, b in edges if adj[a] & adj[b]]
    in_loops = {v for e in looped for v in e}
    core = max(components(n, looped), key=len) if looped else []
    core_max: object = ""
    if len(core) >= 2:
        names = {c.inputs.names[v] for v in core}
        core_max = float(compare_poses({k: v for k, v in est.items() if k in names}, gt).rotation_deg.max())
    ba = c.ba
    tracks3, fewest3 = float("nan"), ""
    if ba is not None and ba.obs_point is not None and len(ba.obs_point):
        length = np.bincount(ba.obs_point)
        tracks3 = float(np.mean(length >= 3))
        fewest3 = int(np.bincount(ba.obs_view[length[ba.obs_point] >= 3], minlength=n).min())
    dev = np.array([x.rotation_deviation_deg for x in c.checks], float)
    prior = c.pairs.focal_prior_px
    f_ratio = c.bundle_focal_px / prior if prior and c.bundle_focal_px else float("nan")
    return [n, len(edges), (len(edges) - (n - 1)) / n, f"{len(in_loops)}/{n}", core_max, tracks3, fewest3,
            f"{np.nanmedian(dev):.2f} / {np.nanmax(dev):.2f}" if np.isfinite(dev).any() else "",
            c.graph.refocused, f_ratio]


def main() -> int:
    draws = int(cli_option("draws", "6"))
    out = cli_option("out", "partial_verdict")
    sets = drs._dtu_sets(draws) + drs._temple_sets()
    if not sets:
        print("no shared data found: nothing to run")
        return 0
    chosen = {}
    solve = api.choose_solution

    def observed(*args, **kwargs):
        result = solve(*args, **kwargs)
        chosen["candidate"] = result[0]
        return result

    api.choose_solution = observed
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for s, _, _, folder, label in drs.prepared(sets, Path(tmp)):
            paths = [p for p in list_images(folder) if p.name in s.gt]
            for partial in (True, False):
                method = "--allow-partial" if partial else "defaults"
                chosen.clear()
                try:
                    res = api.align_images(paths, replace(br.OURS, allow_partial=partial))
                except Exception as exc:  # report, keep going
                    rows.append([label, method, f"0/{len(s.gt)}", "", f"refused: {type(exc).__name__}"]
                                + [""] * 10)
                    print(rows[-1][:5], file=sys.stderr, flush=True)
                    continue
                est = res.sparse_model.cam_from_world_by_name()
                m = compare_poses(est, s.gt)
                worst = float(m.rotation_deg.max())
                rows.append([label, method, f"{m.n_registered}/{m.n_ref}", worst,
                             "**wrong**" if worst > 5.0 else "right"]
                            + _statistics(chosen["candidate"], est, s.gt))
                print(rows[-1], file=sys.stderr, flush=True)
    cpu = subprocess.run("lscpu | grep 'Model name'", shell=True, capture_output=True, text=True).stdout.strip()
    body = (f"Machine: {cpu.split(':', 1)[-1].strip()}, {os.cpu_count()} cores; "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Columns: the script's docstring; `wrong` = a "
            "relative rotation between two registered views more than 5 deg from the reference's.\n\n"
            + md_table(["set", "mvgeo align", "registered", "rot max (deg)", "model", "views", "pairs", "redundancy",
                        "in loops of 3", "loop core max (deg)", "tracks in 3+", "fewest 3+ obs",
                        "pair rot dev med / max (deg)", "refocused", "f / prior"], rows))
    print(write_fragment(out, "Real photographs: what tells a wrong partial model from a right one", body,
                         f"`python benchmarks/diag_partial_verdict.py --draws={draws} --out={out}`"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
