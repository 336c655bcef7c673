"""Which cut-off views a view located by PnP vouches for (`mvgeo.align.checks.views_cut_off(located=...)`):
only itself (`view`, the rule before) against its whole group, joined to it by explained pairs (`group`, the
rule now), on real and synthetic view sets, alternating in one process.

The sets: `diag_real_subsets.py`'s (DTU scan24 clusters around `--draws` random centre views, the temple
ring's five layouts; clean and with Gaussian noise sigma 25/255, noise seed = the set's index; the EXIF focal
a camera would write); `bench_real.py`'s DTU cluster and temple ring with noise seeds 0-5 (the EXIF focal);
the synthetic object_ring (28 training views of 32, 256x192) and llff_like; and object_ring re-quantised with a
dither of 0.5/255 (dither seeds 0..`--dithers`-1, as `diag_accepted_prune.py --sets=ring_dithers`). A row per
set and rule: registered views, the rotation errors over all pairs of registered views, the largest error of
one view (the median of its pairs' errors), ATE over scene scale, seconds.

Usage: .venv/bin/python benchmarks/diag_located_groups.py [--draws=6] [--dithers=8] [--out=NAME]
(writes docs/bench/NAME.md)
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import bench_real as br
import numpy as np
from _common import cli_option, cpu_model, md_table, write_fragment
from diag_real_subsets import _dtu_sets, _temple_sets, prepared

import mvgeo.align.verdict as verdict_module
from mvgeo.align.api import align_images
from mvgeo.align.checks import views_cut_off
from mvgeo.align.loops import rotation_angle_deg
from mvgeo.common.imageio import list_images, read_image, write_image
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


def _only_the_view(checks, bad, n_views, *, located=(), misplaced=()):
    """The rule before: a located view vouches for itself only; the rest of its group stays cut off."""
    return [v for v in views_cut_off(checks, bad, n_views) if v not in set(located)]


def worst_view_deg(est: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> float:
    """The largest over registered views of the median error of its relative rotations to the others (deg)."""
    names = sorted(set(est) & set(gt))
    worst = 0.0
    for a in names:
        errs = [rotation_angle_deg((est[b][:, :3] @ est[a][:, :3].T).T @ (gt[b][:, :3] @ gt[a][:, :3].T))
                for b in names if b != a]
        worst = max(worst, float(np.median(errs)) if errs else 0.0)
    return worst


def align_row(label: str, rule: str, paths: list[Path], gt: dict, extra=lambda res: []) -> list:
    """One `align_images` run with the default benchmark config as a table row: set, rule, registered, rotation
    median and max, worst view, ATE / scale, seconds, `extra(result)` (blank when refused), the refusal."""
    t = time.perf_counter()
    try:
        res = align_images(paths, br.OURS)
    except Exception as exc:  # report, keep going
        return [label, rule, "refused", "", "", "", "", round(time.perf_counter() - t, 2),
                *[""] * len(extra(None)), f"{type(exc).__name__}: {str(exc)[:80]}".replace("|", "/")]
    sec = time.perf_counter() - t
    est = res.sparse_model.cam_from_world_by_name()
    m = compare_poses(est, gt)
    return [label, rule, f"{m.n_registered}/{m.n_ref}", round(m.median_rotation_deg, 3),
            round(float(m.rotation_deg.max()), 3), round(worst_view_deg(est, gt), 2),
            round(m.ate.rmse / br.scene_scale(gt), 5), round(sec, 2), *extra(res), ""]


def compare_rules(jobs, rules: tuple[str, str], run) -> tuple[list[list], str]:
    """`run(label, paths, gt, rule)` for both `rules` on every job, alternating which goes first; (the rows,
    a sentence: the sets whose registered views, errors and ATE differ between the rules, the time of each)."""
    rows = []
    for k, (label, paths, gt) in enumerate(jobs):
        for rule in rules if k % 2 == 0 else rules[::-1]:
            rows.append(run(label, paths, gt, rule))
            print(rows[-1], file=sys.stderr, flush=True)
    pairs = [sorted(rows[k:k + 2], key=lambda r: r[1] != rules[0]) for k in range(0, len(rows), 2)]
    same = sum(a[2:7] == b[2:7] for a, b in pairs)
    changed = [f"{a[0]}: {a[2]} -> {b[2]}" for a, b in pairs if a[2:7] != b[2:7]]
    t = {r: sum(x[7] for x in rows if x[1] == r) for r in rules}
    return rows, (f"Same registered views, rotation errors and ATE on {same} of {len(pairs)} sets"
                  + (f"; changed: {'; '.join(changed)}" if changed else "")
                  + f". Time, all sets: `{rules[0]}` {t[rules[0]]:.1f} s, `{rules[1]}` {t[rules[1]]:.1f} s.\n")


def candidate_starts(res) -> list[str]:
    """`align_row`'s `extra`: one column, the candidates' starts with the chosen one marked."""
    return [""] if res is None else [", ".join(c.start + (" (chosen)" if c.chosen else "")
                                               for c in res.stats.candidates)]


def machine_line() -> str:
    return f"Machine: {cpu_model()}, {os.cpu_count()} cores; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.\n\n"


def dithered_copies(paths: list[Path], out: Path, seed: int) -> list[Path]:
    """The images re-quantised with a dither of 0.5/255 (Gaussian, seed `seed`, then rounded to 8 bits) in `out`."""
    out.mkdir()
    rng = np.random.default_rng(seed)
    for p in paths:
        im = read_image(p)
        write_image(out / p.name, np.clip(np.round((im + rng.normal(0.0, 0.5 / 255, im.shape)) * 255.0) / 255.0,
                                          0.0, 1.0))
    return list_images(out)


def _run(label: str, paths: list[Path], gt: dict, rule: str) -> list:
    verdict_module.views_cut_off = views_cut_off if rule == "group" else _only_the_view
    try:
        return align_row(label, rule, paths, gt)
    finally:
        verdict_module.views_cut_off = views_cut_off


def _jobs(work: Path, draws: int, dithers: int) -> list[tuple[str, list[Path], dict]]:
    jobs = []
    for s, _k, _noisy, folder, label in prepared(_dtu_sets(draws) + _temple_sets(), work / "subsets"):
        jobs.append((label, [p for p in list_images(folder) if p.name in s.gt], s.gt))
    for s in filter(None, (br.dtu_set("cluster"), br.temple_set())):
        e = br.exif_focal_35mm_of(s.K, read_image(s.files[0]).shape[1::-1])
        for seed in range(6):
            f = br.prepare(s, work / "seeds", noisy=True, seed=seed, exif_35mm=e)
            jobs.append((f"{s.name}, sigma 25/255 seed {seed}", [p for p in list_images(f) if p.name in s.gt],
                         s.gt))
    from data_synth import render_scene

    for scene, kw in (("object_ring", dict(size_wh=(256, 192), views=32)), ("llff_like", {})):
        d = render_scene(scene, work / scene, **kw)
        train = json.loads((d / "split.json").read_text())["train"]
        gt = read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()
        paths = [p for p in list_images(d / "images") if p.name in train]
        jobs.append((scene, paths, gt))
        if scene == "object_ring":
            jobs += [(f"object_ring, dither seed {seed}", dithered_copies(paths, work / f"ring_dither{seed}", seed),
                      gt) for seed in range(dithers)]
    return jobs


def main() -> int:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return 0
    draws = int(cli_option("draws", "6"))
    dithers = int(cli_option("dithers", "8"))
    out = cli_option("out", "located_groups")
    with tempfile.TemporaryDirectory() as tmp:
        rows, summary = compare_rules(_jobs(Path(tmp), draws, dithers), ("view", "group"), _run)
    body = (machine_line()
            + md_table(["set", "a located view vouches for", "registered", "rot med (deg)", "rot max (deg)",
                        "worst view (deg)", "ATE / scale", "time (s)", "refused"], rows)
            + "\n\n" + summary)
    print(write_fragment(out, "A located view vouching for itself, or for its group of views", body,
                         f"`python benchmarks/diag_located_groups.py --draws={draws} --dithers={dithers} "
                         f"--out={out}`"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
