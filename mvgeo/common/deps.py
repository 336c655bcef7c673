"""Third-party imports whose order matters, made safe in one place.

Importing `pycolmap` before `cv2` and then writing a PNG with cv2 aborted the
process with a double free (two copies of libpng/zlib symbols resolved in
the wrong order). Importing cv2 first avoids it. Never `import pycolmap`
elsewhere: `from mvgeo.common.deps import pycolmap`. Ruff's banned-api rule
enforces this; `tests/common/test_import_order.py` is the regression test.

The imports are lazy (PEP 562 module `__getattr__`): importing this module
loads nothing; the first `from mvgeo.common.deps import cv2` (or `pycolmap`)
loads cv2, and `pycolmap` always loads cv2 first. So the shared base stays
light (`tests/common/test_import_light.py`) and the order rule still holds
wherever pycolmap is reached through here.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # for type checkers and editors only; at run time `__getattr__` imports them
    import cv2
    import pycolmap

__all__ = ["cv2", "pycolmap"]


def __getattr__(name: str) -> ModuleType:
    if name == "cv2":
        return importlib.import_module("cv2")
    if name == "pycolmap":
        importlib.import_module("cv2")  # must precede pycolmap
        return _import_pycolmap()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _import_pycolmap() -> ModuleType:
    """pycolmap, keeping Python's SIGTERM handler: pycolmap's glog installs a failure signal handler
    at import that answers SIGTERM with a native stack dump (`mvgeo.common.cli` handles SIGTERM)."""
    import signal
    import sys
    import threading

    if "pycolmap" in sys.modules:
        return sys.modules["pycolmap"]
    before = signal.getsignal(signal.SIGTERM)
    module = importlib.import_module("pycolmap")
    if before is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, before)
    return module


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
