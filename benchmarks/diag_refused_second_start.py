"""When the other start is solved (`mvgeo.align.policy._exhausted_start`): only where the first start's candidates
end accepted with a focal that still moves (`drifting`, the rule before), or also where they all end refused
(`refused`, the rule now), on `diag_located_groups.py`'s real and synthetic view sets, alternating in one
process. (The other start for a candidate that contradicts its pairs as a whole is common to both.)

Columns as `diag_located_groups.py`'s, plus the candidates solved and the starts they came from.

Usage: .venv/bin/python benchmarks/diag_refused_second_start.py [--draws=6] [--dithers=8] [--out=NAME]
(writes docs/bench/NAME.md)
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from _common import cli_option, md_table, write_fragment
from diag_located_groups import _jobs, align_row, candidate_starts, compare_rules, machine_line

import mvgeo.align.policy as policy

_refused_too = policy._exhausted_start


def _drifting_only(done, config) -> bool:
    """The rule before: the other start only after accepted candidates whose focal still moves."""
    return any(k.verdict.ok and not policy._focal_consistent(k, config) and k.graph.refocused >= policy.MAX_REFOCUS
               for k in done)


def _run(label: str, paths: list[Path], gt: dict, rule: str) -> list:
    policy._exhausted_start = _refused_too if rule == "refused" else _drifting_only
    try:
        return align_row(label, rule, paths, gt, candidate_starts)
    finally:
        policy._exhausted_start = _refused_too


def main() -> int:
    if "-h" in sys.argv or "--help" in sys.argv:
        print(__doc__)
        return 0
    draws = int(cli_option("draws", "6"))
    dithers = int(cli_option("dithers", "8"))
    out = cli_option("out", "refused_second_start")
    with tempfile.TemporaryDirectory() as tmp:
        rows, summary = compare_rules(_jobs(Path(tmp), draws, dithers), ("drifting", "refused"), _run)
    body = (machine_line()
            + md_table(["set", "other start after", "registered", "rot med (deg)", "rot max (deg)",
                        "worst view (deg)", "ATE / scale", "time (s)", "candidates' starts", "refused"], rows)
            + "\n\n" + summary)
    print(write_fragment(out, "The other start after a drifting focal only, or after refusals too", body,
                         f"`python benchmarks/diag_refused_second_start.py --draws={draws} --dithers={dithers} "
                         f"--out={out}`"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
