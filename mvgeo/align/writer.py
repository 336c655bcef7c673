"""`write_align_result`: OUT/sparse/0 (COLMAP binary), OUT/points.ply and OUT/align.json, atomically."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mvgeo.align.result import AlignResult
from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.output import OutputPlan, as_output_plan
from mvgeo.sparse_model import write_sparse_model

__all__ = ["write_align_result", "write_points_ply"]


def write_align_result(out: str | Path | OutputPlan, result: AlignResult, *, overwrite: bool = False,
                       extra_keys: Mapping[str, Any] | None = None) -> Path:
    """Write `OUT/sparse/0/*.bin`, `OUT/points.ply` and `OUT/align.json` atomically.

    Args:
        out: the folder, or the plan `prepare_output(..., command="mvgeo align")` made for it.
        result: from `align_images`.
        overwrite: a previous `mvgeo align` output at `out` may be replaced (anything else is refused,
            see `mvgeo.common.output`).
        extra_keys: a caller's own records about the alignment (JSON values), written into align.json as
            top-level keys beside `result.stats` (`AlignStats.to_json`). Written here, inside the atomic
            write, so that the output manifest's digest of align.json covers them.

    Returns:
        The folder written.

    Raises:
        InputError: `out` is refused by the output policy.
        ValueError: an extra key is the name of an `AlignStats` field.
    """
    plan = as_output_plan(out, command="mvgeo align", overwrite=overwrite)
    with atomic_output_dir(plan) as tmp:
        write_sparse_model(tmp / "sparse" / "0", result.sparse_model, binary=True)
        write_points_ply(tmp / "points.ply", result.points_xyz, result.points_rgb, result.points_conf)
        result.stats.write(tmp / "align.json", extra_keys=extra_keys)
    return plan.out


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, conf: np.ndarray) -> None:
    """Binary PLY: x y z float32, red green blue uint8, confidence float32 (Open3D reads it)."""
    from plyfile import PlyData, PlyElement

    arr = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1"), ("confidence", "f4")])
    arr["x"], arr["y"], arr["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    arr["red"], arr["green"], arr["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    arr["confidence"] = conf
    PlyData([PlyElement.describe(arr, "vertex")], text=False).write(str(path))
