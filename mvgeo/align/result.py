"""`AlignResult`: what `mvgeo.align.align_images` returns and `write_align_result` writes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvgeo.align.stats import AlignStats
from mvgeo.sparse_model import SparseModel

__all__ = ["AlignResult"]


@dataclass
class AlignResult:
    """Output of `align_images`.

    Attributes:
        sparse_model: PINHOLE cameras at the input resolution, `cam_from_world` per image (names as given),
            and the output point cloud.
        points_xyz: (P, 3) float64 world points; points_rgb: (P, 3) uint8; points_conf: (P,) float32 (>= min_conf).
        stats: the report (`AlignStats`; align.json).
    """

    sparse_model: SparseModel
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    points_conf: np.ndarray
    stats: AlignStats
