"""Which contradicted pairs an accepted candidate is solved again without (`mvgeo.align.policy._prunable`):
every failing pair (`all`, the rule before) against only the pairs whose matches the candidate does not
explain (`unexplained`, the rule now), on many real view sets, alternating in one process.

The sets are `diag_real_subsets.py`'s (DTU scan24 clusters around `--draws` random centre views, the temple
ring's five layouts; clean and with Gaussian noise sigma 25/255, noise seed = the set's index; the EXIF focal
a camera would write), `bench_real.py`'s DTU cluster with noise seeds 0-5, and the synthetic object_ring
(28 training views of 32, 256x192) and llff_like (its own size). For every accepted candidate that a rule
prunes, the pairs it drops are printed (matches, fraction explained, rotation deviation and how well the
matches pin it).

`--sets=ring_dithers` runs object_ring (28 of 32 views) re-quantised with a dither of 0.5/255 (Gaussian, then
rounded to 8 bits; dither seeds 0..`--dithers`-1) instead: what a second exposure's rounding changes.

Usage: .venv/bin/python benchmarks/diag_accepted_prune.py [--sets=real,synthetic|ring_dithers] [--draws=6]
[--dithers=6] [--out=NAME]   (writes docs/bench/NAME.md)
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import bench_real as br
from _common import cli_option, cpu_model, md_table, write_fragment
from diag_located_groups import dithered_copies
from diag_real_subsets import _dtu_sets, _temple_sets, prepared

import mvgeo.align.policy as policy
from mvgeo.align.api import align_images
from mvgeo.common.imageio import list_images, read_image
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model

_new_prunable = policy._prunable
DROPPED: list[str] = []


def _old_prunable(c, config):
    present = {(p.i, p.j) for p in c.pairs.predictions} | {(g.i, g.j) for g in c.pairs.geometries}
    return {(b.i, b.j) for b in c.bad} & present


def _recording(rule):
    def prunable(c, config):
        out = rule(c, config)
        if c.verdict.ok and out:
            DROPPED.append(" ".join(f"({b.i},{b.j}) n={b.n_matches} expl={b.explained_fraction:.2f} "
                                    f"dev={b.rotation_deviation_deg:.1f} std={b.rotation_std_deg:.1f}"
                                    for b in c.bad if (b.i, b.j) in out))
        return out
    return prunable


def _run(label, paths, gt, rule):
    policy._prunable = _recording(_old_prunable if rule == "all" else _new_prunable)
    DROPPED.clear()
    t = time.perf_counter()
    try:
        res = align_images(paths, br.OURS)
    except Exception as exc:
        return [label, rule, "refused", "", "", "", time.perf_counter() - t, "",
                f"{type(exc).__name__}: {str(exc)[:60]}".replace("|", "/")]
    sec = time.perf_counter() - t
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt)
    pruned = len(set(DROPPED))
    return [label, rule, f"{m.n_registered}/{m.n_ref}", round(m.median_rotation_deg, 3),
            round(float(m.rotation_deg.max()), 3), round(m.ate.rmse / br.scene_scale(gt), 5), round(sec, 2),
            len(res.stats.candidates), "; ".join(sorted(set(DROPPED)))[:200] if pruned else ""]


def main() -> int:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return 0
    which = cli_option("sets", "real,synthetic").split(",")
    draws = int(cli_option("draws", "6"))
    dithers = int(cli_option("dithers", "6"))
    out = cli_option("out", "accepted_prune")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        jobs = []
        if "real" in which:
            for s, _k, _noisy, folder, label in prepared(_dtu_sets(draws) + _temple_sets(), work / "subsets"):
                jobs.append((label, [p for p in list_images(folder) if p.name in s.gt], s.gt))
            s = br.dtu_set("cluster")
            e = br.exif_focal_35mm_of(s.K, read_image(s.files[0]).shape[1::-1])
            for seed in range(6):
                f = br.prepare(s, work / "cluster", noisy=True, seed=seed, exif_35mm=e)
                jobs.append((f"dtu_scan24 cluster, sigma 25/255 seed {seed}",
                             [p for p in list_images(f) if p.name in s.gt], s.gt))
        from data_synth import render_scene
        if "synthetic" in which:
            for scene, kw in (("object_ring", dict(size_wh=(256, 192), views=32)), ("llff_like", {})):
                d = render_scene(scene, work / scene, **kw)
                train = json.loads((d / "split.json").read_text())["train"]
                jobs.append((scene, [p for p in list_images(d / "images") if p.name in train],
                             read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()))
        if "ring_dithers" in which:
            d = render_scene("object_ring", work / "ring", size_wh=(256, 192), views=32)
            train = json.loads((d / "split.json").read_text())["train"]
            gt = read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()
            paths = [p for p in list_images(d / "images") if p.name in train]
            jobs += [(f"object_ring, dither seed {seed}", dithered_copies(paths, work / f"ring_dither{seed}", seed), gt)
                     for seed in range(dithers)]
        for k, (label, paths, gt) in enumerate(jobs):
            for rule in ("all", "unexplained") if k % 2 == 0 else ("unexplained", "all"):
                rows.append(_run(label, paths, gt, rule))
                print(rows[-1], file=sys.stderr, flush=True)
    policy._prunable = _new_prunable
    same = sum(a[2:6] == b[2:6] for a, b in zip(rows[::2], rows[1::2], strict=True))
    t = {r: sum(x[6] for x in rows if x[1] == r) for r in ("all", "unexplained")}
    body = (f"Machine: {cpu_model()}, {os.cpu_count()} cores; "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.\n\n"
            + md_table(["set", "accepted candidates pruned of", "registered", "rot med (deg)", "rot max (deg)",
                        "ATE / scale", "time (s)", "candidates", "pairs an accepted candidate was pruned of"], rows)
            + f"\n\nSame registered views, rotation errors and ATE on {same} of {len(rows) // 2} sets; time, all "
              f"sets: `all` {t['all']:.1f} s, `unexplained` {t['unexplained']:.1f} s "
              f"({t['unexplained'] / t['all']:.2f}x).\n")
    title = "Accepted candidates pruned of every failing pair, or of the unexplained ones" + (
        ": object_ring under dither" if which == ["ring_dithers"] else "")
    print(write_fragment(out, title, body,
                         f"`python benchmarks/diag_accepted_prune.py --sets={','.join(which)} --draws={draws} "
                         f"--dithers={dithers} --out={out}`"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
