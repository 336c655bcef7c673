"""Would a classical denoiser in front of `mvgeo align` relate photos its pairs cannot relate at sigma 50/255?

The raw DTU scan24 photos with sigma 50/255 added (`diag_verdict_perturbed.py`'s `dtu_s50:S` sets, no EXIF
focal) are refused by `mvgeo align` on most noise draws (a view on one weak pair, or pairs contradicted),
where pycolmap's global mapper returns more models. Here each set is aligned as it is and after OpenCV's
non-local means (`cv2.fastNlMeansDenoisingColored`, filter strength H on luma and colour, 7 px patches, 21 px
search) on every photo: verdict, rotation error median and max over all pairs of registered views (deg), and
the seconds of the filter and of the alignment. The product itself aligns its denoised photos at that noise
(`--align-photos better_of`); this asks whether `mvgeo align` alone could.

Usage: .venv/bin/python benchmarks/diag_nlm_features.py [--sets=dtu_s50:0,dtu_s50:1,dtu_s50:2,dtu_s50:3]
[--strengths=0,20,40]   (strength 0: the photos as they are)
"""

from __future__ import annotations

import time
from pathlib import Path

from _common import cli_option, md_table
from bench_real import OURS
from diag_verdict_perturbed import each_set

from mvgeo.align.api import align_images
from mvgeo.common.deps import cv2
from mvgeo.common.errors import AlignmentRefusedError, DegenerateGeometryError, DisconnectedViewsError
from mvgeo.metrics import compare_poses


def _filtered(paths: list[Path], out: Path, strength: float) -> tuple[list[Path], float]:
    """The photos after non-local means of `strength` (8-bit PNGs in `out`), and the filter's seconds."""
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    res = []
    for p in paths:
        img = cv2.imread(str(p))
        if strength > 0:
            img = cv2.fastNlMeansDenoisingColored(img, None, strength, strength, 7, 21)
        cv2.imwrite(str(out / p.name), img)
        res.append(out / p.name)
    return res, time.perf_counter() - t


def main() -> int:
    sets = cli_option("sets", "dtu_s50:0,dtu_s50:1,dtu_s50:2,dtu_s50:3").split(",")
    strengths = [float(s) for s in cli_option("strengths", "0,20,40").split(",")]
    rows = []
    for name, work, paths, gt, _ in each_set(sets):
        for h in strengths:
            files, filter_s = _filtered(paths, work / f"{name.replace(':', '_')}_nlm{h:g}", h)
            t = time.perf_counter()
            try:
                res = align_images(files, OURS)
            except AlignmentRefusedError as exc:
                rows.append([name, h, f"refused: {exc.kind}", "", "", filter_s, time.perf_counter() - t])
                continue
            except (DegenerateGeometryError, DisconnectedViewsError) as exc:
                rows.append([name, h, f"failed: {type(exc).__name__}", "", "", filter_s, time.perf_counter() - t])
                continue
            m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt)
            rows.append([name, h, f"accepted, {m.n_registered}/{m.n_ref}", m.median_rotation_deg,
                         float(m.rotation_deg.max()), filter_s, time.perf_counter() - t])
            print(rows[-1], flush=True)
    print(md_table(["set", "NLM strength", "verdict", "rot med (deg)", "rot max (deg)", "filter (s)", "align (s)"],
                   rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
