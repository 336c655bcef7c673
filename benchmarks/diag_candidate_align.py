"""Whether each candidate needs the global alignment's iterations before its bundle adjustment.

`AlignConfig.candidate_align_iters`: the global-alignment iterations a candidate runs between its start
(chained pairs or rotation + translation averaging) and its bundle adjustment (default None: all of
`AlignConfig.align.iters`, 100); with fewer, the full alignment runs once, for the chosen candidate's cloud,
where the cloud uses its depth maps. This runs `mvgeo align` without the dense stereo (`bench_real.OURS`:
poses and sparse points, as pycolmap's mappers return; the cloud then comes from the full alignment, so its
time is counted) with 0 and with all 100 candidate iterations, alternating, REPEATS times each, on: DTU
scan24 cluster (clean;
sigma 25/255 noise seeds 0-5; seeds 0-2 also with the calibration given), the temple ring (clean), DTU
scan24 spread (clean: refused either way), and the synthetic `llff_like` and `object_ring` (12 views,
rendered here). Prints one row per run: set, variant, registered, rotation error median / max (deg),
translation-direction error (deg), ATE / scale, focal error %, seconds, note; then the mean seconds per set
and variant, and their ratio.

With `--stereo`, `mvgeo align`'s defaults instead (the dense stereo on: the product's cloud, which uses
the full alignment's depth maps only for a view the stereo leaves empty).

Usage: OMP_WAIT_POLICY=PASSIVE python benchmarks/diag_candidate_align.py [REPEATS] [--stereo]
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_real as br  # noqa: E402  (its own imports put cv2 before pycolmap)

from mvgeo.align.config import AlignConfig  # noqa: E402
from mvgeo.common.imageio import read_image  # noqa: E402
from mvgeo.sparse_model import read_sparse_model  # noqa: E402


def _synthetic(work: Path):
    from data_synth import render_scene

    for name in ("llff_like", "object_ring"):
        d = render_scene(name, work / name, views=12)
        ref = read_sparse_model(d / "sparse" / "0")
        gt = {n: np.asarray(T)[:3] for n, T in ref.cam_from_world_by_name().items()}
        yield name, d / "images", gt, float(ref.cameras[ref.images[0].camera_id].fx)


def main(argv: list[str]) -> int:
    stereo = "--stereo" in argv
    argv = [a for a in argv if a != "--stereo"]
    repeats = int(argv[0]) if argv else 1
    base = AlignConfig() if stereo else br.OURS
    variants = {"0": dataclasses.replace(base, candidate_align_iters=0), "100 (default)": base}
    work = Path(tempfile.mkdtemp(prefix="diag_candidate_align_"))
    runs = []  # (label, folder, gt, f_ref, intrinsics file or None)
    cluster, temple, spread = br.dtu_set("cluster"), br.temple_set(), br.dtu_set("spread")
    if cluster is not None:
        for seed in [None, 0, 1, 2, 3, 4, 5]:
            folder = br.prepare(cluster, work, noisy=seed is not None, seed=seed or 0)
            label = f"{cluster.name}, {'clean' if seed is None else f'sigma 25, seed {seed}'}"
            runs.append((label, folder, cluster.gt, float(cluster.K[0, 0]), None))
            if seed is not None and seed <= 2:
                wh = read_image(next(iter(sorted(folder.glob("*.png"))))).shape[1::-1]
                txt = br.write_cameras_txt(cluster.K, wh, work / f"cameras_{seed}.txt")
                runs.append((label + ", calibrated", folder, cluster.gt, float(cluster.K[0, 0]), txt))
    for s in (temple, spread):
        if s is not None:
            runs.append((f"{s.name}, clean", br.prepare(s, work, noisy=False), s.gt, float(s.K[0, 0]), None))
    runs += [(name, folder, gt, f, None) for name, folder, gt, f in _synthetic(work)]
    print("| set | candidate iterations | registered | rot med | rot max | transl dir | ATE / scale | focal err % "
          "| s | note |\n|---|---|---|---|---|---|---|---|---|---|")
    seconds: dict[tuple[str, str], list[float]] = {}
    for label, folder, gt, f_ref, intr in runs:
        for rep in range(repeats):
            for name in (list(variants) if rep % 2 == 0 else list(reversed(variants))):
                r = br.run_ours(label, name, folder, gt, f_ref, intr, variants[name])
                seconds.setdefault((label, name), []).append(float(r[8]))
                cells = [f"{x:.4g}" if isinstance(x, float) else str(x) for x in r[:9]] + [str(r[11])[:110]]
                print("| " + " | ".join(cells) + " |", flush=True)
    print("\n| set | 0 (s) | 100 (s) | ratio |\n|---|---|---|---|")
    for label, *_ in runs:
        a, b = np.mean(seconds[(label, "0")]), np.mean(seconds[(label, "100 (default)")])
        print(f"| {label} | {a:.2f} | {b:.2f} | {a / b:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
