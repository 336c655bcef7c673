"""When the other start is solved (`mvgeo.align.policy._exhausted_start`): only where the first start's candidates
end accepted with a focal that still moves (`drifting`, the rule before), or also where they all end refused
(`refused`, the rule now), on `diag_located_groups.py`'s real and synthetic view sets, alternating in one
process. (The other start for a candidate that contradicts its pairs as a whole is common to both.)

Columns as `diag_located_groups.py`'s, plus the candidates solved and the starts they came from.

Usage: .venv/bin/python benchmarks/diag_refused_second_start.py [--draws=6] [--dithers=8] [--out=NAME]
(writes docs/bench/NAME.md)
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import bench_real as br
from _common import cli_option, cpu_model, md_table, write_fragment
from diag_located_groups import _jobs, worst_view_deg

import mvgeo.align.policy as policy
from mvgeo.align.api import align_images
from mvgeo.metrics import compare_poses

_refused_too = policy._exhausted_start


def _drifting_only(done, config) -> bool:
    """The rule before: the other start only after accepted candidates whose focal still moves."""
    return any(k.verdict.ok and not policy._focal_consistent(k, config) and k.graph.refocused >= policy.MAX_REFOCUS
               for k in done)


def _run(label: str, paths: list[Path], gt: dict, rule: str) -> list:
    policy._exhausted_start = _refused_too if rule == "refused" else _drifting_only
    t = time.perf_counter()
    try:
        res = align_images(paths, br.OURS)
    except Exception as exc:  # report, keep going
        return [label, rule, "refused", "", "", "", "", round(time.perf_counter() - t, 2), "",
                f"{type(exc).__name__}: {str(exc)[:80]}".replace("|", "/")]
    finally:
        policy._exhausted_start = _refused_too
    sec = time.perf_counter() - t
    est = res.sparse_model.cam_from_world_by_name()
    m = compare_poses(est, gt)
    starts = ", ".join(c.start + (" (chosen)" if c.chosen else "") for c in res.stats.candidates)
    return [label, rule, f"{m.n_registered}/{m.n_ref}", round(m.median_rotation_deg, 3),
            round(float(m.rotation_deg.max()), 3), round(worst_view_deg(est, gt), 2),
            round(m.ate.rmse / br.scene_scale(gt), 5), round(sec, 2), starts, ""]


def main() -> int:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return 0
    draws = int(cli_option("draws", "6"))
    dithers = int(cli_option("dithers", "8"))
    out = cli_option("out", "refused_second_start")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (label, paths, gt) in enumerate(_jobs(Path(tmp), draws, dithers)):
            for rule in ("drifting", "refused") if k % 2 == 0 else ("refused", "drifting"):
                rows.append(_run(label, paths, gt, rule))
                print(rows[-1], file=sys.stderr, flush=True)
    pairs = [sorted(rows[k:k + 2], key=lambda r: r[1] != "drifting") for k in range(0, len(rows), 2)]
    same = sum(a[2:7] == b[2:7] for a, b in pairs)
    changed = [f"{a[0]}: {a[2]} -> {b[2]}" for a, b in pairs if a[2:7] != b[2:7]]
    t = {r: sum(x[7] for x in rows if x[1] == r) for r in ("drifting", "refused")}
    body = (f"Machine: {cpu_model()}, {os.cpu_count()} cores; "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.\n\n"
            + md_table(["set", "other start after", "registered", "rot med (deg)", "rot max (deg)",
                        "worst view (deg)", "ATE / scale", "time (s)", "candidates' starts", "refused"], rows)
            + f"\n\nSame registered views, rotation errors and ATE on {same} of {len(pairs)} sets"
            + (f"; changed: {'; '.join(changed)}" if changed else "")
            + f". Time, all sets: `drifting` {t['drifting']:.1f} s, `refused` {t['refused']:.1f} s.\n")
    print(write_fragment(out, "The other start after a drifting focal only, or after refusals too", body,
                         f"`python benchmarks/diag_refused_second_start.py --draws={draws} --dithers={dithers} "
                         f"--out={out}`"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
