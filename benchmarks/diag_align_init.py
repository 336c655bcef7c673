"""The global alignment's two initialisations side by side: DUSt3R's chained pointmaps and the pairs' own poses.

For each scene, `mvgeo align` (dense stereo off) from the "chain" start and from the "averaged" start
(`AlignConfig.initial_poses`), each alone (`AlignConfig.second_start` off), scored against ground truth:
registered views, median relative rotation error (deg), ATE. Scenes are those of `bench_align.py`
(`llff_like`, `subsets`, `temple`, `object_ring`, `dtu`; temple and object_ring with `--allow-partial`), the
data_synth scenes named, and any dataset folder given as `dir:PATH` (its `split.json` training views against
its `sparse/0`), e.g. an N2V round's photos copied into a dataset layout.

Run: `.venv/bin/python benchmarks/diag_align_init.py SCENES` with SCENES =
`llff_like,subsets,dtu,temple,object_ring,hard_highnoise,poisson,hard_tinybaseline,hard_repetitive` (prints a
markdown table; the current one is in docs/bench/align.md).
"""

from __future__ import annotations

import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from _common import md_table
from bench_align import DEFAULT, scenes

from mvgeo.align.api import align_images
from mvgeo.align.dense_stereo import DenseStereoConfig
from mvgeo.common.imageio import list_images
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model

BENCH_SCENES = ("llff_like", "object_ring", "temple", "dtu", "subsets")
SYNTH_SCENES = ("hard_highnoise", "poisson", "hard_tinybaseline", "hard_lowtexture", "hard_repetitive",
                "llff_like_clean")


def _row(scene: str, init: str, paths, ref, partial: bool) -> list:
    cfg = replace(DEFAULT, dense_stereo=DenseStereoConfig(enabled=False), second_start=False, allow_partial=partial,
                  initial_poses=init)
    try:
        res = align_images(paths, cfg)
    except Exception as exc:  # report, keep going
        return [scene, init, f"failed: {type(exc).__name__}: {exc}"[:120], "", ""]
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), ref)
    return [scene, init, f"{m.n_registered}/{m.n_ref}", m.median_rotation_deg,
            m.ate.rmse if m.ate is not None else float("nan")]


def main() -> None:
    if len(sys.argv) != 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        return
    which = sys.argv[1].split(",")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        jobs = []
        for scene, images, ref, _ in scenes(Path(tmp), [w for w in which if w in BENCH_SCENES]):
            paths = [p for p in list_images(images) if p.name in ref]
            jobs.append((scene, paths, ref, scene.startswith(("temple", "object"))))
        from data_synth import render_scene

        for name in [w for w in which if w in SYNTH_SCENES]:
            d = render_scene(name, Path(tmp) / name, views=12)
            ref = read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()
            jobs.append((name, list_images(d / "images"), ref, False))
        for folder in [w[4:] for w in which if w.startswith("dir:")]:
            d = Path(folder)
            train = json.loads((d / "split.json").read_text())["train"]
            jobs.append((folder, [d / "images" / n for n in train],
                         read_sparse_model(d / "sparse" / "0").cam_from_world_by_name(), False))
        for scene, paths, ref, partial in jobs:
            for init in ("chain", "averaged"):
                rows.append(_row(scene, init, paths, ref, partial))
                print(rows[-1], file=sys.stderr, flush=True)
    print(md_table(["scene", "initialisation", "registered", "rot err (deg)", "ATE"], rows))


if __name__ == "__main__":
    main()
