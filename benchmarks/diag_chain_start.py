"""The "auto" start rule's measurement, scene by scene: how much the chained start contradicts the pairs, and
what each start gives when solved alone.

For each scene: the pair graph of `mvgeo align` (defaults), the chained start's initial values
(`mvgeo.align.init.initial_values`), the fraction of the verified pairs whose own relative rotation is more than
`AlignConfig.max_pair_rotation_deg` from the chained start's (`chain_contradicted_fraction`, the rule's
measure; `CHAIN_MAX_CONTRADICTED` is its limit) and the median of those angles; then one candidate from each start
(`mvgeo.align.solve.solve`: global alignment, bundle adjustment, verdict; no pruning, no second start) with its
verdict and its rotation error against ground truth (median / max over the view pairs, deg).

Scenes: the real sets of `bench_real.py` (`temple`, `dtu_cluster`, `dtu_spread`; 12 views, clean and with
sigma 25/255 for noise seeds 0..N-1, `--noise-seeds`, each with the EXIF focal a camera would write) and
data_synth scenes (`synth:NAME` at 12 views; `synth:object_ring@256` is object_ring's 21 training views at
256x192, `synth:object_ring@256x32` its 28 of 32). `mvgeo align` runs without the dense stereo (`bench_real.OURS`:
it does not change the poses).

Run: `.venv/bin/python benchmarks/diag_chain_start.py temple,dtu_cluster,synth:object_ring,... [--noise-seeds=2]`
(prints a markdown table; the current one is in docs/bench/align.md).
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import bench_real as br
import numpy as np
from _common import md_table

from mvgeo.align.classical_pairs import ClassicalPointmapModel
from mvgeo.align.config import AlignConfig
from mvgeo.align.graph import make_pairs
from mvgeo.align.init import chain_contradicted_fraction, choose_start, pair_relative_rotations
from mvgeo.align.inputs import load_inputs
from mvgeo.align.intrinsics import choose_focal_prior
from mvgeo.align.rotation_averaging import relative_rotation_residuals_deg
from mvgeo.align.solve import pair_graph, pairs_K_align, solve, start_values
from mvgeo.common.imageio import list_images, read_image
from mvgeo.common.timing import StageTimer
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


def _row(scene: str, paths: list[Path], gt: dict, cfg: AlignConfig) -> list:
    inputs = load_inputs(paths, names=None, intrinsics=None, max_size_px=cfg.max_size_px)
    prior, _ = choose_focal_prior(paths, known_intrinsics=False, given=None, read_exif=cfg.exif_focal)
    model = ClassicalPointmapModel(cfg.pairwise, seed=cfg.seed,
                                   focal_prior_px=None if prior is None else prior.focal_px(inputs.align_wh))
    pairs = model.predict_pairs(inputs.small, make_pairs(len(inputs), cfg.pairs))
    timer = StageTimer()
    try:
        graph = pair_graph(inputs, pairs, cfg, timer)
    except Exception as exc:  # report, keep going
        return [scene, "", "", f"no pair graph: {type(exc).__name__}"[:60], "", ""]
    chain = start_values(graph, "chain", cfg)
    rotations = pair_relative_rotations(graph.pairs, pairs_K_align(graph.inputs, graph.pairs))
    frac = chain_contradicted_fraction(chain.init.cam_from_world, rotations, cfg.max_pair_rotation_deg)
    med = float(np.median(list(relative_rotation_residuals_deg(chain.init.cam_from_world[:, :, :3],
                                                               rotations).values())))
    out = []
    for start in ("chain", "averaged"):
        try:
            c = solve(graph, start, cfg, timer, values=chain if start == "chain" else None)
        except Exception as exc:  # report, keep going
            out.append(f"failed: {type(exc).__name__}")
            continue
        m = compare_poses(dict(zip(c.inputs.names, c.result.cam_from_world, strict=True)), gt)
        verdict = "accepted" if c.verdict.ok else "refused (" + ", ".join(r.kind for r in c.verdict.reasons) + ")"
        out.append(f"{verdict}; {m.median_rotation_deg:.2f} / {float(m.rotation_deg.max()):.1f} deg")
    return [scene, f"{frac:.2f}", f"{med:.1f}", *out, choose_start("auto", frac)]


def _synth(spec: str, work: Path):
    from data_synth import render_scene

    name, _, variant = spec.partition("@")
    kw = {"views": 12} if not variant else {"size_wh": (256, 192)}
    if variant.endswith("x32"):
        kw["views"] = 32
    d = render_scene(name, work / spec.replace("@", "_"), **kw)
    gt = read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()
    train = json.loads((d / "split.json").read_text())["train"] if variant else sorted(gt)
    return [p for p in list_images(d / "images") if p.name in train], {k: v for k, v in gt.items() if k in train}


def main() -> int:
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    seeds = int(next((a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--noise-seeds=")), "1"))
    if len(args) != 1:
        print(__doc__)
        return 2
    cfg = br.OURS  # poses only: the dense stereo does not change them
    real = {"temple": br.temple_set, "dtu_cluster": lambda: br.dtu_set("cluster"),
            "dtu_spread": lambda: br.dtu_set("spread")}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for which in args[0].split(","):
            if which.startswith("synth:"):
                paths, gt = _synth(which[6:], work)
                rows.append(_row(which, paths, gt, cfg))
                print(rows[-1], file=sys.stderr, flush=True)
                continue
            s = real[which]()
            if s is None:
                print(f"note: {which} missing, skipped", file=sys.stderr)
                continue
            wh = read_image(s.files[0]).shape[1::-1]
            for noisy, seed in [(False, 0)] + [(True, k) for k in range(seeds)]:
                folder = br.prepare(s, work, noisy, seed, br.exif_focal_35mm_of(s.K, wh))
                label = f"{s.name}, " + (f"sigma 25/255 (seed {seed})" if noisy else "clean")
                rows.append(_row(label, [p for p in list_images(folder) if p.name in s.gt], s.gt, cfg))
                print(rows[-1], file=sys.stderr, flush=True)
    print(md_table(["scene", "pairs the chained start contradicts", "median pair angle (deg)",
                    "chain start alone: verdict; rot err med / max", "averaged start alone", "rule's first start"],
                   rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
