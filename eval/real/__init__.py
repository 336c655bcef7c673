"""Real photographs with known cameras -> the project's dataset layout, with declared degradations only.

Readers (`llff`, `colmap_model`, `middlebury`, `dtu`) return a `Capture` in
the project's conventions (docs/conventions.md); `layout.write_capture`
chooses the split, resizes, degrades and writes; `api.import_dataset` does
both (the `denoise-gs dataset import` command).
"""

from eval.real.api import KINDS, import_dataset, read_capture
from eval.real.capture import BoundingSphere, Capture, CaptureView
from eval.real.degrade import Degradation, DegradationStep, parse_noise
from eval.real.layout import ImportConfig, write_capture

__all__ = [
    "KINDS",
    "BoundingSphere",
    "Capture",
    "CaptureView",
    "Degradation",
    "DegradationStep",
    "ImportConfig",
    "import_dataset",
    "parse_noise",
    "read_capture",
    "write_capture",
]
