"""Track completion: guided matches on the pairs the verification did not keep, then the bundle adjustment again.

`mvgeo align` adjusts the poses on the tracks of its verified pairs. On DTU scan24 with noise, one view
(000007) has few of them and carries the largest rotation errors. Here, after an alignment as
`benchmarks/bench_real.py` runs it (`ours`: the EXIF focal, no dense stereo), the chosen candidate's
adjusted poses define every unverified pair's epipolar geometry; guided matching
(`mvgeo.align.guided.guided_matches`, Lowe's ratio 0.8 within a band of `--bands` px) finds those pairs'
matches, pairs with at least 15 are added to the verified pairs' matches, and the bundle adjustment runs once
more from the adjusted poses. Printed per noise draw and band: the rotation error median / max (deg, over all
pairs of views) and ATE / scene scale of the alignment as returned and of the completed adjustment, its
tracks, and the seconds of the guided matching and of the adjustment.

Run: `OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/diag_track_completion.py [--seeds=clean,0,1,2]
[--bands=1,2,3]` (needs ../shared/data).
"""

from __future__ import annotations

import itertools
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import cli_option, md_table
from bench_real import OURS, dtu_for_script, exif_focal_35mm_of, prepare, scene_scale

import mvgeo.align.solve as solve
from mvgeo.align.api import align_images
from mvgeo.align.bundle import bundle_adjust
from mvgeo.align.guided import fundamental_from_pose, guided_matches
from mvgeo.common.imageio import list_images, read_image
from mvgeo.metrics import compare_poses

MIN_MATCHES = 15


def _K(f: float, W: int, H: int) -> np.ndarray:
    return np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])


def _errors(est: dict, gt: dict) -> tuple[float, float, float]:
    m = compare_poses(est, gt)
    return m.median_rotation_deg, float(m.rotation_deg.max()), m.ate.rmse / scene_scale(gt)


def main() -> int:
    s = dtu_for_script(__doc__)
    if s is None:
        return 0
    draws = cli_option("seeds", "clean,0,1,2").split(",")
    bands = [float(b) for b in cli_option("bands", "1,2,3").split(",")]
    adjusted = []  # every candidate's adjustment, in order: the chosen one is the last that ran before the cloud
    original = solve.adjust_and_judge

    def spy(*args, **kwargs):
        c = original(*args, **kwargs)
        adjusted.append(c)
        return c

    solve.adjust_and_judge = spy
    wh = read_image(s.files[0]).shape[1::-1]
    rows = []
    with tempfile.TemporaryDirectory(prefix="diag-completion-") as tmp:
        for draw in draws:
            noisy = draw != "clean"
            folder = prepare(s, Path(tmp) / draw, noisy, int(draw) if noisy else 0, exif_focal_35mm_of(s.K, wh))
            paths = [p for p in list_images(folder) if p.name in s.gt]
            adjusted.clear()
            res = align_images(paths, OURS)
            final = res.sparse_model.cam_from_world_by_name()
            label = "clean" if not noisy else f"sigma 25, seed {draw}"
            med, mx, ate = _errors(final, s.gt)
            ba = res.stats.bundle_adjustment
            rows.append([label, "as returned", f"{med:.3f}", f"{mx:.3f}", f"{ate:.4f}", ba.n_points, "", "", ""])
            print(" | ".join(map(str, rows[-1])), flush=True)
            names = res.sparse_model.names
            c = next(c for c in reversed(adjusted) if c.ba is not None and list(c.inputs.names) == list(names))
            T, f = c.ba.cam_from_world, c.ba.focal_px
            W, H = c.inputs.align_wh
            feats = [c.graph.pairs.features[c.graph.inputs.names.index(n)] for n in c.inputs.names]
            matches = solve.ideal_matches(c.pairs.matches, c.inputs.K_align, c.inputs.align_wh)
            verified = {(i, j) for i, j, _ in matches}
            for band in bands:
                t = time.perf_counter()
                extra = []
                for a, b in itertools.combinations(range(len(feats)), 2):
                    if (a, b) in verified or (b, a) in verified:
                        continue
                    R = T[b][:, :3] @ T[a][:, :3].T
                    tr = T[b][:, 3] - R @ T[a][:, 3]
                    m = guided_matches(feats[a].uv_px, feats[a].root(), feats[b].uv_px, feats[b].root(),
                                       fundamental_from_pose(R, tr, _K(f[a], W, H), _K(f[b], W, H)), band_px=band)
                    if len(m) >= MIN_MATCHES:
                        extra.append((a, b, np.hstack([feats[a].uv_px[m[:, 0]], feats[b].uv_px[m[:, 1]]])))
                t_match = time.perf_counter() - t
                t = time.perf_counter()
                cfg = replace(OURS.bundle, shared_focal=OURS.bundle.shared_focal or c.align_config.shared_focal)
                done = bundle_adjust(T, f, c.inputs.align_wh, list(matches) + extra, config=cfg)
                t_ba = time.perf_counter() - t
                est = {n: done.cam_from_world[k] for k, n in enumerate(c.inputs.names)}
                med, mx, ate = _errors(est, s.gt)
                rows.append([label, f"completed, band {band:g} px", f"{med:.3f}", f"{mx:.3f}", f"{ate:.4f}",
                             done.n_points, len(extra), f"{t_match:.2f}", f"{t_ba:.2f}"])
                print(" | ".join(map(str, rows[-1])), flush=True)
    print(md_table(["draw", "poses", "rot med (deg)", "rot max (deg)", "ATE / scale", "tracks", "pairs added",
                    "guided s", "adjustment s"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
