"""Shared base for every package and CLI: typed errors, logging, progress,
stage timing, atomic output folders, safe third-party imports and image I/O.

This is the lowest layer of the project; it imports nothing from the other
packages. It is light: importing it, or any of its modules, loads no cv2,
pycolmap or torch and sets no environment variable (those load on first use;
the command lines set the thread policy with
`mvgeo.common.threads.apply_thread_policy`). `tests/common/test_import_light.py`
checks every module.
"""

from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.errors import (
    AlignmentRefusedError,
    ConfigError,
    DegenerateGeometryError,
    DgsError,
    DisconnectedViewsError,
    InputError,
    ShapeError,
    check_shape,
)
from mvgeo.common.timing import StageTimer

__all__ = [
    "AlignmentRefusedError",
    "ConfigError",
    "DegenerateGeometryError",
    "DgsError",
    "DisconnectedViewsError",
    "InputError",
    "ShapeError",
    "StageTimer",
    "atomic_output_dir",
    "check_shape",
]
