"""The principal point `mvgeo align` estimates (`mvgeo.align.principal`), against the calibration's, and what
it does to the rotations: each set aligned with `AlignConfig.principal_point` "centre" and "auto" (the
default) on the same images.

Usage: .venv/bin/python benchmarks/diag_principal_point.py [--sets=temple,dtu,dtu_noisy,llff_like]
[--dither=none,0,1,2] [--out=NAME]

The sets, the dither and the EXIF focal as in `diag_verdict_perturbed.py` (12 views, poses only). Columns: set,
dither seed, the calibration's principal point offset from the image centre (px, input size), the estimate's
offset and standard deviation, whether it was kept (and the rule's figures), and the median / max rotation
error over all pairs (deg) with the centre, with "auto", and with the estimate kept whatever the rule says
(`mvgeo.align.principal.determined` replaced by one that always agrees: what the rule protects from).
"""

from __future__ import annotations

import sys
from dataclasses import replace

from _common import cli_option, md_table, write_fragment
from bench_real import OURS, exif_focal_35mm_of
from diag_verdict_perturbed import _variant, each_set

import mvgeo.align.principal as principal
from mvgeo.align.api import align_images
from mvgeo.common.imageio import read_image
from mvgeo.metrics import compare_poses


def main() -> int:
    sets = cli_option("sets", "temple,dtu,dtu_noisy,llff_like").split(",")
    dithers = cli_option("dither", "none,0,1,2").split(",")
    rows = []
    for name, work, paths, gt, K in each_set(sets):
        h, w = read_image(paths[0]).shape[:2]
        true_off = f"{K[0, 2] - w / 2:+.1f}, {K[1, 2] - h / 2:+.1f}"
        for seed in dithers:
            tagged = _variant(paths, work / f"{name}_{seed}", exif_focal_35mm_of(K, (w, h)), seed)
            errs = {}
            for mode in ("centre", "auto", "always"):
                rule = principal.determined
                if mode == "always":
                    principal.determined = lambda offset, std, f, rule=rule: (True, rule(offset, std, f)[1])
                try:
                    res = align_images(tagged, replace(OURS, principal_point="centre" if mode == "centre"
                                                       else "auto"))
                finally:
                    principal.determined = rule
                m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt)
                errs[mode] = f"{m.median_rotation_deg:.3f} / {float(m.rotation_deg.max()):.2f}"
                if mode == "auto":
                    pp = res.stats.principal_point
            kept = "" if pp is None else ("kept" if pp.kept else "centre") + ": " + pp.reason.split(": ", 1)[-1]
            rows.append([name, seed, true_off,
                         "" if pp is None else f"{pp.offset_px[0]:+.1f}, {pp.offset_px[1]:+.1f}",
                         "" if pp is None else f"{pp.std_px[0]:.1f}, {pp.std_px[1]:.1f}",
                         kept, errs["centre"], errs["auto"], errs["always"]])
            print(" | ".join(str(x) for x in rows[-1]), flush=True)
    table = md_table(["set", "dither seed", "true offset (px)", "estimated offset (px)", "its std (px)",
                      "kept? (the rule's figures)", "rot med / max, centre (deg)", "rot med / max, auto (deg)",
                      "rot med / max, kept regardless (deg)"], rows)
    out = cli_option("out", "")
    if out:
        write_fragment(out, "The principal point", table,
                       "`python benchmarks/diag_principal_point.py " + " ".join(sys.argv[1:]) + "`")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
