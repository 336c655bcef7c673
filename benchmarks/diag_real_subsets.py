"""Many real view sets from the two shared captures: `mvgeo align` against pycolmap global mapping on each.

`bench_real.py` runs one 12-view layout per capture; the product is judged on captures it has not seen, so
this draws more of them from the same photographs:

- `dtu`: DTU scan24's 49 views; for each of `--draws` seeded draws, a centre view at random and its 11
  nearest views by viewing direction (a forward-facing cluster somewhere on the dome, about 10-15 deg between
  neighbours);
- `temple`: the Middlebury temple ring's 16 views (about 22 deg apart, one position duplicated): all 16; 12
  consecutive views of the ring starting at each of four positions (an arc, no loop closure); every other
  view (8 views, about 45 deg apart).

Each set clean and with Gaussian noise sigma 25/255 (noise seed = draw), every image carrying the EXIF focal
a camera would write (as `bench_real.py --exif`). Columns as `bench_real.py` (registered, rotation error
median and max over the view pairs, ATE over the scene scale, seconds), plus which start `mvgeo align` chose
and the fraction of pairs its chained start contradicts (`mvgeo.align.init.choose_start`). A summary counts,
per method, the sets with every view, the views registered, the sets with a view more than 5 deg off (a
relative rotation between two registered views more than 5 deg from the reference's), and the time ratio.

With `--partial`, `mvgeo align --allow-partial` runs too (the largest group it can connect and verify, as
pycolmap returns partial models).

Run: `.venv/bin/python benchmarks/diag_real_subsets.py [--sets=dtu,temple] [--draws=6] [--partial]
[--out=real_subsets]` (writes docs/bench/NAME.md).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import bench_real as br
import numpy as np
from _common import cli_option, md_table, write_fragment

from mvgeo.align.api import align_images
from mvgeo.common.imageio import list_images, read_image
from mvgeo.metrics import compare_poses


def _dtu_sets(draws: int) -> list[br.RealSet]:
    from eval.datasets import dtu_cameras

    if not (br.DTU / "cameras.npz").is_file():
        print(f"note: {br.DTU} missing, DTU skipped", file=sys.stderr)
        return []
    files = sorted((br.DTU / "images").glob("*.png"))
    cams = dtu_cameras(br.DTU / "cameras.npz", len(files))
    dirs = np.stack([T[2, :3] for _, T in cams])
    out = []
    for d in range(draws):
        centre = int(np.random.default_rng(100 + d).integers(len(files)))
        pick = sorted(np.argsort(-(dirs @ dirs[centre]))[:br.N_VIEWS].tolist())
        K = np.median(np.stack([cams[v][0] for v in pick]), axis=0)
        out.append(br.RealSet(f"dtu_scan24 around view {centre}", [files[v] for v in pick],
                              {files[v].name: cams[v][1] for v in pick}, K))
    return out


def _temple_sets() -> list[br.RealSet]:
    from eval.real.middlebury import read_middlebury

    if not (br.TEMPLE / "templeSR_par.txt").is_file():
        print(f"note: {br.TEMPLE} missing, temple skipped", file=sys.stderr)
        return []
    views = read_middlebury(br.TEMPLE).views
    cams = np.stack([v.cam_from_world[:3] for v in views])
    C = -np.einsum("nji,nj->ni", cams[:, :, :3], cams[:, :, 3])
    centre = C.mean(axis=0)
    # Order the views around the ring by azimuth about the ring's axis (the normal of the centres' best plane);
    # views at one position (the ring has a duplicate) in file order.
    axis = np.linalg.svd(C - centre)[2][2]
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    azimuth = np.round(np.arctan2((C - centre) @ e2, (C - centre) @ e1), 3)
    ring = np.lexsort((np.arange(len(views)), azimuth)).tolist()

    def make(label, pick):
        gt = {views[v].image_path.name: cams[v] for v in pick}
        K = np.median(np.stack([views[v].camera.K for v in pick]), axis=0)
        return br.RealSet(f"temple, {label}", [views[v].image_path for v in sorted(pick)], gt, K)

    n = len(ring)
    sets = [make(f"all {n}", ring)]
    sets += [make(f"arc of 12 from ring position {s}", [ring[(s + k) % n] for k in range(12)]) for s in (0, 4, 8, 12)]
    sets.append(make(f"every other ({n // 2})", ring[::2]))
    return sets


def prepared(sets: list[br.RealSet], work: Path) -> Iterator[tuple[br.RealSet, int, bool, Path, str]]:
    """Each set clean and noisy (noise seed = the set's index), as image files in `work` with the EXIF focal
    a camera would write: (set, index, noisy, folder, label)."""
    for k, s in enumerate(sets):
        wh = read_image(s.files[0]).shape[1::-1]
        for noisy in (False, True):
            folder = br.prepare(s, work / f"set{k}", noisy, k, br.exif_focal_35mm_of(s.K, wh))
            yield s, k, noisy, folder, f"{s.name}, " + ("sigma 25/255" if noisy else "clean")


def _ours(label: str, folder: Path, s: br.RealSet, partial: bool = False) -> list:
    paths = [p for p in list_images(folder) if p.name in s.gt]
    method = "ours --allow-partial" if partial else "ours"
    t = time.perf_counter()
    try:
        res = align_images(paths, replace(br.OURS, allow_partial=partial))
    except Exception as exc:  # report, keep going
        return [label, method, f"0/{len(s.gt)}", "", "", "", time.perf_counter() - t, "",
                f"failed: {type(exc).__name__}: {str(exc)[:90]}".replace("|", "/")]
    sec = time.perf_counter() - t
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), s.gt)
    st = res.stats
    frac = "" if st.chain_start_contradicted is None else f"{st.chain_start_contradicted:.2f}"
    return [label, method, f"{m.n_registered}/{m.n_ref}", m.median_rotation_deg, float(m.rotation_deg.max()),
            m.ate.rmse / br.scene_scale(s.gt) if m.ate is not None else float("nan"), sec, frac,
            f"{st.initial_poses} start, {len(st.candidates)} candidates"]


def _global(label: str, folder: Path, s: br.RealSet) -> list:
    row = br.run_pycolmap(label, "global", folder, s.gt, float(s.K[0, 0]))
    registered = row[2] if row[3] != "" else f"0/{len(s.gt)}"  # `failed_row` assumes 12 views
    return [label, "pycolmap global", registered, row[3], row[4], row[6], row[8], "", row[11]]


def main() -> int:
    which = cli_option("sets", "dtu,temple").split(",")
    draws = int(cli_option("draws", "6"))
    out = cli_option("out", "real_subsets")
    partial = "--partial" in sys.argv
    sets = (_dtu_sets(draws) if "dtu" in which else []) + (_temple_sets() if "temple" in which else [])
    if not sets:
        print("no shared data found: nothing to run")
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for s, k, noisy, folder, label in prepared(sets, Path(tmp)):
            runs = ["ours", "global"] + (["partial"] if partial else [])
            for run in runs if (k + noisy) % 2 == 0 else runs[::-1]:  # alternate which runs first
                rows.append(_global(label, folder, s) if run == "global" else
                            _ours(label, folder, s, partial=run == "partial"))
                print(rows[-1], file=sys.stderr, flush=True)
    summary = []
    methods = ["ours", "pycolmap global"] + (["ours --allow-partial"] if partial else [])
    for method in methods:
        mine = [r for r in rows if r[1] == method]
        full = sum(r[2].split("/")[0] == r[2].split("/")[1] for r in mine)
        views = sum(int(r[2].split("/")[0]) for r in mine)
        off = sum(isinstance(r[4], float) and r[4] > 5.0 for r in mine)
        t = sum(r[6] for r in mine)
        summary.append([method, f"{full}/{len(mine)}", f"{views}/{sum(len(s.gt) for s in sets) * 2}", off, t])
    t_global = summary[1][4]
    for r in summary:
        r.append(r[4] / t_global if t_global else float("nan"))
    cpu = subprocess.run("lscpu | grep 'Model name'", shell=True, capture_output=True, text=True).stdout.strip()
    body = (f"Machine: {cpu.split(':', 1)[-1].strip()}, {os.cpu_count()} cores; "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.\n\n"
            + md_table(["set", "method", "registered", "rot med (deg)", "rot max (deg)", "ATE / scale", "time (s)",
                        "pairs the chained start contradicts", "note"], rows)
            + "\n\n" + md_table(["method", "sets with every view", "views registered", "sets with a view > 5 deg off",
                                 "time (s), all",
                                 "time / pycolmap global"], summary))
    flags = " --partial" if partial else ""
    print(write_fragment(out, "Real photographs: many view sets of the shared captures", body,
                         f"`python benchmarks/diag_real_subsets.py --sets={','.join(which)} --draws={draws}{flags} "
                         f"--out={out}`"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
