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
import tempfile
from pathlib import Path

import numpy as np

import eval.cli  # noqa: F401  first: the thread policy and cv2 before pycolmap
from mvgeo.sparse_model import read_sparse_model

ROOT = Path(__file__).resolve().parents[1]


def _rot(T) -> np.ndarray:
    return np.asarray(T.matrix() if hasattr(T, "matrix") else T)[:3, :3]


def _errors(model_dir: Path, reference: Path) -> str:
    est = read_sparse_model(model_dir).cam_from_world_by_name()
    ref = read_sparse_model(reference).cam_from_world_by_name()
    names = sorted(n for n in est if n in ref)
    n = len(names)
    err = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            d = (_rot(est[names[j]]) @ _rot(est[names[i]]).T) @ (_rot(ref[names[j]]) @ _rot(ref[names[i]]).T).T
            err[i, j] = err[j, i] = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1)))
    per_view = [float(np.median(np.delete(err[i], i))) for i in range(n)]
    worst = int(np.argmax(per_view))
    iu = np.triu_indices(n, 1)
    C_e = np.array([-_rot(est[m]).T @ np.asarray(est[m].matrix() if hasattr(est[m], "matrix") else est[m])[:3, 3]
                    for m in names])
    C_r = np.array([-_rot(ref[m]).T @ np.asarray(ref[m].matrix() if hasattr(ref[m], "matrix") else ref[m])[:3, 3]
                    for m in names])
    ate = _ate_over_scale(C_e, C_r)
    return (f"{n} views, {np.median(err[iu]):.2f} deg, worst view {per_view[worst]:.1f} deg ({names[worst]}), "
            f"ATE/scale {ate:.4f}")


def _ate_over_scale(C_e: np.ndarray, C_r: np.ndarray) -> float:
    """RMSE of the centres after the least-squares similarity (Umeyama), over the reference's RMS spread."""
    me, mr = C_e.mean(0), C_r.mean(0)
    E, R_ = C_e - me, C_r - mr
    U, S, Vt = np.linalg.svd(R_.T @ E)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    Rm = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (E ** 2).sum()
    aligned = s * E @ Rm.T + mr
    scale = np.sqrt((R_ ** 2).sum(1).mean())
    return float(np.sqrt(((aligned - C_r) ** 2).sum(1).mean()) / scale)


def _align(checkout: Path, images: Path, out: Path, reference: Path) -> str:
    run = subprocess.run([sys.executable, "-m", "mvgeo.cli", "align", str(images), "--out", str(out),
                          "--no-dense-stereo"], cwd=checkout, capture_output=True, text=True)
    if run.returncode != 0:
        last = [ln for ln in run.stderr.splitlines() if "rror" in ln or "refus" in ln]
        return "refused: " + (last[-1] if last else run.stderr.strip()[-200:])[:160]
    return _errors(out / "sparse" / "0", reference)


def main(base: str, datasets: list[Path]) -> int:
    work = Path(tempfile.mkdtemp(prefix="align_ab_"))
    base_tree = work / "base"
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(base_tree), base], cwd=ROOT, check=True)
    try:
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
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(base_tree)], cwd=ROOT, check=False)
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    if len(sys.argv) < 3:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    sys.exit(main(sys.argv[1], [Path(p) for p in sys.argv[2:]]))
