"""Third-party imports whose order matters, made safe in one place.

Importing `pycolmap` before `cv2` and then writing a PNG with cv2 aborted the
process with a double free (two copies of libpng/zlib symbols resolved in
the wrong order). Importing cv2 first avoids it. Never `import pycolmap`
elsewhere: `from mvgeo.common.deps import pycolmap`. Ruff's banned-api rule
enforces this; `tests/common/test_import_order.py` is the regression test.

It is also the first module every package imports, so it sets the OpenMP wait
policy before torch (or OpenCV) starts its thread pool: with the default
(spinning) policy, torch's idle intra-op threads busy-wait between the many
small ops of a training step, and on a loaded 2-core machine that made N2V
training 1.7x slower with 2 threads than with 1 and splat training up to ~20x
slower; with `OMP_WAIT_POLICY=PASSIVE` the same 2-thread N2V run was 3.7x
faster than spinning (docs/benchmarks.md, "Threads"). A value the user set is kept.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import cv2  # noqa: F401  (must precede pycolmap)
import pycolmap  # noqa: E402

__all__ = ["cv2", "pycolmap"]
