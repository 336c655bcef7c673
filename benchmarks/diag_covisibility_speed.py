"""The dense cloud's co-visibility pruning (`mvgeo.align.scene.covisibility_keep`): each view's points in
chunks of `scene._CHUNK` against the whole view at once, on the calls `mvgeo align` makes.

The call is recorded while `mvgeo align` (EXIF focal) aligns DTU scan24's 12 clustered training views with
Gaussian noise sigma 25/255 (noise seed 0), with the dense stereo (the product's default: 256 x 256 depth
maps) and without it (the global alignment's 128 x 128 depth maps, `bench_real.py`'s `ours`). The two
settings then run the same call alternating REPEATS times (default 5), on the default threads; the masks
must be equal.

Usage: .venv/bin/python benchmarks/diag_covisibility_speed.py [REPEATS]   (needs ../shared/data)
"""
from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import cpu_model, recorded_calls
from bench_real import OURS, dtu_for_script, exif_focal_35mm_of, prepare

import mvgeo.align.cloud as cloud
import mvgeo.align.scene as scene
from mvgeo.align.api import align_images
from mvgeo.align.dense_stereo import DenseStereoConfig
from mvgeo.common.imageio import list_images, read_image


def main() -> int:
    s = dtu_for_script(__doc__)
    if s is None:
        return 0
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    chunk = scene._CHUNK
    print(f"{cpu_model()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; chunk {chunk} points")
    with tempfile.TemporaryDirectory() as tmp:
        folder = prepare(s, Path(tmp), noisy=True, seed=0,
                         exif_35mm=exif_focal_35mm_of(s.K, read_image(s.files[0]).shape[1::-1]))
        paths = [p for p in list_images(folder) if p.name in s.gt]
        for label, cfg in (("dense stereo (256 x 256)", replace(OURS, dense_stereo=DenseStereoConfig())),
                           ("without it (128 x 128)", OURS)):
            with recorded_calls(cloud, "covisibility_keep") as calls:
                align_images(paths, cfg)
            args, kwargs = calls[0]
            sec = {"whole views": [], "chunked": []}
            masks = {}
            for _ in range(repeats):
                for name, size in (("whole views", 1 << 40), ("chunked", chunk)):
                    scene._CHUNK = size
                    t = time.perf_counter()
                    masks[name] = scene.covisibility_keep(*args, **kwargs)
                    sec[name].append(time.perf_counter() - t)
            scene._CHUNK = chunk
            same = all(np.array_equal(a, b) for a, b in zip(masks["whole views"], masks["chunked"], strict=True))
            w, c = np.median(sec["whole views"]), np.median(sec["chunked"])
            print(f"{label}: whole views {w:.3f} s, chunked {c:.3f} s (medians of {repeats}); {w / c:.2f}x; "
                  f"masks equal: {same}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
