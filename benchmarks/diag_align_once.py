"""Round 1's alignment of photos the denoise stage passed through: aligned once, or twice as before.

Under `--align-photos better_of` round 1 aligns the noisy photos and the denoised ones and keeps the better
determined. Where the denoise stage passed the photos through (`pass_clean_below_255`), the two are the same
pixels, and `eval.pipeline.align_stage.same_photos` has them aligned once. This runs the stage's
`_align_first_round` on one folder of photos given as both, once each way, alternating, and prints the
seconds and whether the kept poses are the same.

Usage: .venv/bin/python benchmarks/diag_align_once.py DATASET [--repeats=2]
(DATASET: an imported dataset folder; its training views are aligned, e.g. runs/real/dtu24_cluster12_clean).
"""
import json
import sys
import time
from pathlib import Path

from _common import cli_option

import eval.cli  # noqa: F401  first: sets the thread policy before torch loads


def main() -> int:
    import numpy as np

    from eval.pipeline.align_stage import _align_first_round, same_photos
    from eval.pipeline.config import PRESETS
    from eval.pipeline.stage_settings import align_config
    from mvgeo.align import align_images

    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if len(args) != 1:
        print(__doc__.strip().splitlines()[-2], file=sys.stderr)
        return 2
    root = Path(args[0])
    repeats = int(cli_option("repeats", "2"))
    files = [root / "images" / n for n in json.loads((root / "split.json").read_text())["train"]]
    noisy = {f.stem: f for f in files}
    cfg = align_config(PRESETS["default"].align, seed=0)  # the stage also passes its focal prior, if any
    t = time.perf_counter()
    same = same_photos(files, noisy)
    print(f"same_photos: {same} in {time.perf_counter() - t:.3f} s")
    seconds = {True: [], False: []}
    kept = {}
    for _ in range(repeats):
        for identical in (False, True):
            t = time.perf_counter()
            res = _align_first_round(align_images, files, noisy, cfg, keep_better=True, identical=identical)
            seconds[identical].append(time.perf_counter() - t)
            kept[identical] = res
    poses = {k: v.alignment.sparse_model.cam_from_world_by_name() for k, v in kept.items()}
    diff = max(float(np.abs(poses[True][n] - poses[False][n]).max()) for n in poses[True])
    print("| photos aligned | seconds (each run) | kept | largest pose difference to twice |")
    print("|---|---|---|---|")
    for identical in (False, True):
        print(f"| {'once' if identical else 'twice'} | {', '.join(f'{s:.1f}' for s in seconds[identical])} | "
              f"{kept[identical].decisions.photos.aligned} | {diff if identical else 0:.2e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
