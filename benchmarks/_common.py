"""Helpers for benchmark scripts: timing, peak memory, writing a fragment, a worktree of a base commit."""

from __future__ import annotations

import contextlib
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


@contextlib.contextmanager
def base_worktree(commit: str, prefix: str = "base_") -> Iterator[Path]:
    """A temporary detached `git worktree` of `commit` (the code to compare this checkout with), inside a
    temporary folder that the caller may use for its own files too; both removed at the end of the block.
    Yields the worktree's path (its parent is the temporary folder)."""
    work = Path(tempfile.mkdtemp(prefix=prefix))
    tree = work / "base"
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(tree), commit], cwd=ROOT, check=True)
    try:
        yield tree
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, check=False)
        shutil.rmtree(work, ignore_errors=True)


@contextlib.contextmanager
def recorded_calls(owner: object, name: str) -> Iterator[list[tuple[tuple, dict]]]:
    """Record every call of `owner.name` (a module's or class's function) made inside the block, as
    (args, kwargs); the calls still run. The function is restored at the end of the block."""
    real = getattr(owner, name)
    calls: list[tuple[tuple, dict]] = []

    def spy(*args, **kwargs):
        calls.append((args, kwargs))
        return real(*args, **kwargs)

    setattr(owner, name, spy)
    try:
        yield calls
    finally:
        setattr(owner, name, real)


def time_call(fn: Callable[[], object], *, repeat: int = 3, warmup: int = 1) -> float:
    """Median wall time in seconds of `fn()` over `repeat` runs after `warmup`."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    times.sort()
    return times[len(times) // 2]


def first_train_views(data: Path, n: int):
    """The first `n` training views of a dataset folder (`splat.dataset.load_views`, split "train")."""
    from splat.dataset import load_views

    views = load_views(data, split="train")
    keep = list(range(len(views.names)))[:n]
    views.names = [views.names[i] for i in keep]
    views.images = [views.images[i] for i in keep]
    views.cameras = [views.cameras[i] for i in keep]
    views.cam_from_world = views.cam_from_world[keep]
    return views


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB (Linux ru_maxrss is KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_model() -> str:
    """The CPU's model name (Linux `/proc/cpuinfo`), else what `platform` knows."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown CPU"


def md_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    def fmt(x: object) -> str:
        if isinstance(x, float):
            return f"{x:.4g}"
        return str(x)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def write_fragment(name: str, title: str, body: str, reproduce: str | None = None) -> Path:
    """Write docs/bench/<name>.md: a section with the command that reproduces it (`reproduce`, default
    `make bench ONLY=<name>`; a script's run with options under another name says so)."""
    path = ROOT / "docs" / "bench" / f"{name}.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    text = f"## {title}\n\nReproduce: {reproduce or f'`make bench ONLY={name}`'}\n\n{body.rstrip()}\n"
    path.write_text(text)
    return path


def cli_option(key: str, default: str) -> str:
    """The value of `--key=VALUE` on this script's command line, or `default`."""
    vals = [a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith(f"--{key}=")]
    return vals[0] if vals else default


def held_out_at_true_poses(round_dir: Path, dataset) -> dict[str, float]:
    """Mean held-out PSNR / SSIM / LPIPS of a splat trained with the true cameras (`round_dir/point_cloud.ply`),
    scored as `denoise-gs eval` scores its `@gt_poses` rows (true held-out poses, clean images).

    Args:
        dataset: the `DatasetFolder` it was trained from (its `sparse/0` holds the true cameras).
    """
    from eval.evaluate import EvalConfig, _score_scene
    from mvgeo.sparse_model import read_sparse_model
    from splat.ply import read_gaussian_ply

    model = read_gaussian_ply(Path(round_dir) / "point_cloud.ply", device="cpu")
    gt = read_sparse_model(dataset.root / "sparse" / "0")
    per_view, _ = _score_scene(model, gt, None, dataset, EvalConfig())
    return {key: sum(v[key] for v in per_view.values()) / len(per_view) for key in ("psnr_db", "ssim", "lpips")}
