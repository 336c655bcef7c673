"""Shared base for every package and CLI: typed errors, logging, progress,
stage timing, atomic output folders, safe third-party imports and image I/O.

This is the lowest layer of the project; it imports nothing from the other
packages.
"""

from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.errors import (
    ConfigError,
    DegenerateGeometryError,
    DgsError,
    InputError,
    ShapeError,
    check_shape,
)
from mvgeo.common.timing import StageTimer

__all__ = [
    "ConfigError",
    "DegenerateGeometryError",
    "DgsError",
    "InputError",
    "ShapeError",
    "StageTimer",
    "atomic_output_dir",
    "check_shape",
]
