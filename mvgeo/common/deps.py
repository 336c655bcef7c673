"""Third-party imports whose order matters, made safe in one place.

Importing `pycolmap` before `cv2` and then writing a PNG with cv2 aborted the
process with a double free (two copies of libpng/zlib symbols resolved in
the wrong order). Importing cv2 first avoids it. Never `import pycolmap`
elsewhere: `from mvgeo.common.deps import pycolmap`. Ruff's banned-api rule
enforces this; `tests/common/test_import_order.py` is the regression test.
"""

import cv2  # noqa: F401  (must precede pycolmap)
import pycolmap  # noqa: E402

__all__ = ["cv2", "pycolmap"]
