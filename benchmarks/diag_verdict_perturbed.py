"""Does the alignment's verdict hold under perturbations that should not matter? `mvgeo align` on the same
images re-quantised with a little dither (Gaussian, 0.5/255, then rounded to 8 bits: what a second exposure's
rounding would change) and with starting focals off by a percent or two (the EXIF focal length is whole
millimetres: 74 mm carries +-0.7 %): every accepted result's rotation errors, every refusal's kind.

Usage: .venv/bin/python benchmarks/diag_verdict_perturbed.py [--sets=object_ring,llff_like,temple,dtu,dtu_noisy]
[--dither=none,0,1,2] [--focal-scales=1.0] [--methods=ours,global] [--out=NAME]

`global` runs pycolmap's global mapper (GLOMAP; `bench_real.run_pycolmap`, reading the same EXIF focal) on the
same files. The issue's contract: a result or a named refusal, never a view more than 5 deg off. Columns: set,
method, dither
seed (none: the images as they are), focal scale, verdict (accepted / the refusal's kind), registered,
rotation error median and max over all pairs of registered views (deg), seconds. The synthetic sets are
rendered by `data_synth.render_scene` (12 views);
`temple` and `dtu` are `bench_real.py`'s (12 views, poses only, clean; `dtu_noisy`: sigma 25/255, noise
seed 0), with the EXIF focal their calibration implies times the focal scale (0: no EXIF).
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from _common import cli_option, md_table, write_fragment
from bench_real import OURS, dtu_set, exif_focal_35mm_of, prepare, run_pycolmap, temple_set

from mvgeo.align.api import align_images
from mvgeo.common.errors import AlignmentRefusedError, DegenerateGeometryError, DisconnectedViewsError
from mvgeo.common.imageio import list_images, read_image, write_image
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model


def _synthetic(name: str, work: Path):
    from data_synth import render_scene

    d = render_scene(name, work / name, views=12)
    ref = read_sparse_model(d / "sparse" / "0")
    gt = ref.cam_from_world_by_name()
    K = ref.camera_of(next(iter(gt))).K
    return list_images(d / "images"), gt, K


def set_images(name: str, work: Path) -> tuple[list[Path], dict[str, np.ndarray], np.ndarray] | None:
    """(image files, {name: reference cam_from_world}, calibration K) of a set named as `--sets` names them
    (written under `work`), or None where ../shared/data lacks it. `dtu_noisy:S` is `dtu_noisy` with noise seed
    S; `dtu_s50:S` the DTU images with sigma 50/255 added, noise seed S."""
    if name in ("object_ring", "llff_like"):
        return _synthetic(name, work)
    s = temple_set() if name == "temple" else dtu_set("cluster")
    if s is None:
        return None
    kind, _, seed = name.partition(":")
    if kind == "dtu_s50":
        folder = work / name.replace(":", "_")
        folder.mkdir(parents=True)
        rng = np.random.default_rng(int(seed or 0))
        for f in s.files:
            img = np.round(read_image(f) * 255.0) / 255.0
            write_image(folder / f.name, np.clip(img + rng.normal(0.0, 50.0 / 255.0, img.shape), 0.0, 1.0))
    else:
        folder = prepare(s, work / name.replace(":", "_"), noisy=kind == "dtu_noisy", seed=int(seed or 0))
    return [p for p in list_images(folder) if p.name in s.gt], s.gt, s.K


def each_set(names: list[str]) -> Iterator[tuple[str, Path, list[Path], dict[str, np.ndarray], np.ndarray]]:
    """(name, working folder, image files, reference poses, K) of every set of `names` that `set_images` has,
    written under a temporary working folder removed afterwards; a set ../shared/data lacks is announced and
    skipped."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for name in names:
            got = set_images(name, work)
            if got is None:
                print(f"{name}: ../shared/data missing, skipped")
                continue
            yield (name, work, *got)


def _variant(paths: list[Path], out: Path, mm: int | None, dither: str) -> list[Path]:
    """The images, dithered with seed `dither` (unless "none"), as 8-bit PNGs carrying EXIF focal `mm` (unless
    None)."""
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    rng = None if dither == "none" else np.random.default_rng(int(dither))
    res = []
    for p in paths:
        img = np.round(read_image(p) * 255.0)
        if rng is not None:
            img = np.round(img + rng.normal(0.0, 0.5, img.shape))
        write_image(out / p.name, np.clip(img, 0, 255) / 255.0)
        if mm is not None:
            exif = Image.Exif()
            exif.get_ifd(0x8769)[0xA405] = int(mm)
            with Image.open(out / p.name) as im:
                im.load()
                im.save(out / p.name, exif=exif.tobytes())
        res.append(out / p.name)
    return res


def _ours_row(name, seed, scale, tagged, gt) -> list:
    """`mvgeo align`'s row (`bench_real.OURS`) for one variant of a set."""
    label = "ours"
    t = time.perf_counter()
    try:
        res = align_images(tagged, OURS)
    except AlignmentRefusedError as exc:
        return [name, label, seed, scale, f"refused: {exc.kind}", "0/12", "", "", time.perf_counter() - t]
    except (DegenerateGeometryError, DisconnectedViewsError) as exc:
        why = f"failed: {type(exc).__name__}: {str(exc)[:80]}"
        return [name, label, seed, scale, why, "0/12", "", "", time.perf_counter() - t]
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt)
    rot = m.rotation_deg
    return [name, label, seed, scale, "accepted", f"{m.n_registered}/{m.n_ref}", m.median_rotation_deg,
            float(rot.max()) if rot.size else float("nan"), time.perf_counter() - t]


def _summary(rows: list[list]) -> str:
    """Per set and method: runs, results returned, views registered (mean), median of the returned results'
    median rotation errors, the largest max, and how many returned a pair more than 5 deg off."""
    out = []
    for key in dict.fromkeys((r[0], r[1]) for r in rows):
        mine = [r for r in rows if (r[0], r[1]) == key]
        got = [r for r in mine if r[6] != "" and not str(r[5]).startswith("0/")]
        meds = [float(r[6]) for r in got]
        maxs = [float(r[7]) for r in got]
        views = [int(str(r[5]).split("/")[0]) for r in mine]
        out.append([key[0], key[1], len(mine), len(got), float(np.mean(views)) if views else 0.0,
                    float(np.median(meds)) if meds else float("nan"), max(maxs) if maxs else float("nan"),
                    sum(m > 5.0 for m in maxs)])
    return md_table(["set", "method", "runs", "returned a model", "views registered (mean)",
                     "rot med: median (deg)", "rot max: largest (deg)", "returned with a pair > 5 deg off"], out)


def main() -> int:
    sets = cli_option("sets", "object_ring,llff_like,temple,dtu,dtu_noisy").split(",")
    dithers = cli_option("dither", "none,0,1,2").split(",")
    scales = [float(s) for s in cli_option("focal-scales", "1.0").split(",")]
    methods = cli_option("methods", "ours").split(",")
    rows = []
    for name, work, paths, gt, K in each_set(sets):
        h, w = read_image(paths[0]).shape[:2]
        for scale in scales:
            # scale 0: no EXIF (the pairs' focal consensus or COLMAP's prior)
            mm = None if scale == 0 else exif_focal_35mm_of(K * np.diag([scale, scale, 1.0]), (w, h))
            for seed in dithers:
                tagged = _variant(paths, work / f"{name}_{scale}_{seed}", mm, seed)
                if "global" in methods:
                    r = run_pycolmap(name, "global", tagged[0].parent, gt, float(K[0, 0]))
                    verdict = r[11] if r[2] == "0/12" and r[11] else "returned"
                    rows.append([name, "pycolmap global", seed, scale, verdict, r[2], r[3], r[4], r[8]])
                    print(" | ".join(str(x) for x in rows[-1]), flush=True)
                if "ours" not in methods:
                    continue
                rows.append(_ours_row(name, seed, scale, tagged, gt))
                print(" | ".join(str(x) for x in rows[-1]), flush=True)
    table = md_table(["set", "method", "dither seed", "focal scale", "verdict", "registered", "rot med (deg)",
                      "rot max (deg)", "s"], rows)
    table += "\n\n" + _summary(rows)
    out = cli_option("out", "")
    if out:
        write_fragment(out, "The verdict under dither and starting focals", table,
                       "`python benchmarks/diag_verdict_perturbed.py " + " ".join(sys.argv[1:]) + "`")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
