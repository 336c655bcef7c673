"""`mvgeo align` of a base commit against this checkout on dataset folders: what a change to the alignment does
to real view sets, view by view.

For each dataset folder (the project's layout: `images/`, `split.json`, `sparse/0` with the reference cameras)
the training views are aligned by both checkouts (`python -m mvgeo.cli align`, each run in its own checkout, the
base in a temporary `git worktree`), alternating, and each result is compared with the reference cameras:
registered views, the median relative rotation error over all pairs (deg), the worst view (the median of its
pairs' errors) and the ATE over the scene scale, or the refusal's first words.

Usage: .venv/bin/python benchmarks/diag_align_checkouts.py BASE_COMMIT DATASET [DATASET ...]
(e.g. folders made by `denoise-gs dataset import dtu ../shared/data/dtu_scan24 --out D --views 12 --test 4
--layout cluster --noise gaussian:50 --seed K`)
"""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from _common import ROOT, base_worktree
from bench_real import scene_scale

import eval.cli  # noqa: F401  first: the thread policy and cv2 before pycolmap
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


def _errors(model_dir: Path, reference: Path) -> str:
    """`compare_poses` on the registered views, and the worst view (the median of its pairs' errors)."""
    est = read_sparse_model(model_dir).cam_from_world_by_name()
    ref = {n: T for n, T in read_sparse_model(reference).cam_from_world_by_name().items() if n in est}
    m = compare_poses(est, ref)
    n = len(m.names)
    err = np.zeros((n, n))
    err[np.triu_indices(n, 1)] = m.rotation_deg  # `relative_pose_errors`' pair order
    err += err.T
    per_view = [float(np.median(np.delete(err[i], i))) for i in range(n)]
    worst = int(np.argmax(per_view))
    ate = m.ate.rmse / scene_scale(ref) if m.ate is not None else float("nan")
    return (f"{n} views, {m.median_rotation_deg:.2f} deg, worst view {per_view[worst]:.1f} deg "
            f"({m.names[worst]}), ATE/scale {ate:.4f}")


def _align(checkout: Path, images: Path, out: Path, reference: Path) -> str:
    run = subprocess.run([sys.executable, "-m", "mvgeo.cli", "align", str(images), "--out", str(out),
                          "--no-dense-stereo"], cwd=checkout, capture_output=True, text=True)
    if run.returncode != 0:
        last = [ln for ln in run.stderr.splitlines() if "rror" in ln or "refus" in ln]
        return "refused: " + (last[-1] if last else run.stderr.strip()[-200:])[:160]
    return _errors(out / "sparse" / "0", reference)


def main(base: str, datasets: list[Path]) -> int:
    with base_worktree(base, prefix="align_ab_") as base_tree:
        work = base_tree.parent
        print(f"| set | base `{base}` | this checkout |")
        print("|---|---|---|")
        for k, ds in enumerate(datasets):
            train = json.loads((ds / "split.json").read_text())["train"]
            images = work / f"images_{k}"
            images.mkdir()
            for p in sorted((ds / "images").iterdir()):
                if p.name in train or p.stem in train:
                    shutil.copy2(p, images / p.name)
            order = [("base", base_tree), ("this", ROOT)]
            if k % 2:
                order.reverse()
            row = {who: _align(tree, images, work / f"out_{who}_{k}", ds / "sparse" / "0") for who, tree in order}
            print(f"| {ds.name} | {row['base']} | {row['this']} |", flush=True)
    return 0


if __name__ == "__main__":
    if len(sys.argv) < 3:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    sys.exit(main(sys.argv[1], [Path(p) for p in sys.argv[2:]]))
