"""Run benchmarks and assemble docs/benchmarks.md.

Usage: `make bench` (all) or `make bench ONLY="splat denoise"`;
`python benchmarks/run_all.py --assemble` only rebuilds docs/benchmarks.md from the fragments.

Each `benchmarks/bench_<name>.py` is run as its own process (so one's memory
and threads do not disturb another's) and writes `docs/bench/<name>.md`, which
states the command that reproduces it. This script then concatenates every
fragment under a header describing the machine.
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FRAGMENTS = ROOT / "docs" / "bench"


def machine_line() -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"{os.cpu_count()} cores ({cpu}), Python {platform.python_version()}, torch {torch.__version__}, "
            f"torch threads {torch.get_num_threads()}")


_LINK = re.compile(r"(\]\()([^)\s]+)(\))")


def relink(text: str) -> str:
    """A fragment of docs/bench/ with its relative links rewritten for docs/benchmarks.md, one folder up:
    `x.md` -> `bench/x.md`, `../x` -> `x`; absolute, anchor-only and URL links stay."""
    def fix(m: re.Match) -> str:
        target = m.group(2)
        if target.startswith(("#", "/", "http://", "https://", "mailto:")):
            return m.group(0)
        target = target[3:] if target.startswith("../") else "bench/" + target
        return m.group(1) + target + m.group(3)

    return _LINK.sub(fix, text)


def main(argv: list[str]) -> int:
    from mvgeo.common.threads import apply_thread_policy

    apply_thread_policy()  # the benchmark processes inherit OMP_WAIT_POLICY, as under the command lines
    assemble_only = "--assemble" in argv
    only = {a for a in argv if a != "--assemble"}
    scripts = sorted((ROOT / "benchmarks").glob("bench_*.py"))
    if only:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in only]
        missing = only - {s.stem.removeprefix("bench_") for s in scripts}
        if missing:
            print(f"error: no benchmark named {', '.join(sorted(missing))}", file=sys.stderr)
            return 2
    FRAGMENTS.mkdir(parents=True, exist_ok=True)
    failed = []
    if assemble_only:
        scripts = []
    for script in scripts:
        print(f"== {script.name}", flush=True)
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, str(script)], cwd=ROOT)
        print(f"   {script.name}: exit {proc.returncode} in {time.perf_counter() - start:.0f} s", flush=True)
        if proc.returncode != 0:
            failed.append(script.name)
    parts = [
        "# Benchmarks\n",
        "Produced by `make bench` (all) or `make bench ONLY=<name>` (one section); each section names "
        "the command that reproduces it. Timings are wall-clock on a shared machine: compare ratios "
        "measured in the same run, not absolute numbers across sections.\n",
        f"Last machine: {machine_line()}.\n",
    ]
    for frag in sorted(FRAGMENTS.glob("*.md")):
        parts.append(relink(frag.read_text().rstrip()) + "\n")
    (ROOT / "docs" / "benchmarks.md").write_text("\n".join(parts))
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
