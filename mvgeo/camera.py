"""Camera intrinsics (COLMAP camera models) — conventions in docs/conventions.md.

`Camera` holds a COLMAP model name, the image size and the parameters in
COLMAP's order, with the principal point in our pixel convention (the
top-left pixel's centre is (0.5, 0.5), as in COLMAP).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mvgeo.common.errors import InputError

#: COLMAP model name -> parameter names, in COLMAP's order.
CAMERA_MODEL_PARAMS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


@dataclass
class Camera:
    """Intrinsics of one camera.

    Attributes:
        model: COLMAP model name, one of `CAMERA_MODEL_PARAMS`.
        width: image width in pixels.
        height: image height in pixels.
        params: (P,) float64, COLMAP order for `model`; cx, cy with the top-left
            pixel centre at (0.5, 0.5).
    """

    model: str
    width: int
    height: int
    params: np.ndarray = field(repr=True)

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODEL_PARAMS:
            raise InputError(f"unknown camera model {self.model!r}",
                             fix=f"use one of {', '.join(CAMERA_MODEL_PARAMS)}")
        self.params = np.asarray(self.params, dtype=np.float64).reshape(-1)
        expected = len(CAMERA_MODEL_PARAMS[self.model])
        if self.params.shape != (expected,):
            raise InputError(f"camera model {self.model} takes {expected} parameters "
                             f"({', '.join(CAMERA_MODEL_PARAMS[self.model])}), got {self.params.size}")
        self.width = int(self.width)
        self.height = int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera size must be positive, got {self.width}x{self.height}")

    # -- pinhole part -------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.params[0])

    @property
    def fy(self) -> float:
        return float(self.params[0] if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL") else self.params[1])

    @property
    def cx(self) -> float:
        return float(self.params[1] if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL") else self.params[2])

    @property
    def cy(self) -> float:
        return float(self.params[2] if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL") else self.params[3])

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 pinhole matrix (distortion, if any, is not in it)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size_wh(self) -> tuple[int, int]:
        return (self.width, self.height)

    @classmethod
    def pinhole(cls, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> Camera:
        """A PINHOLE camera (cx, cy in our convention)."""
        return cls("PINHOLE", width, height, np.array([fx, fy, cx, cy], dtype=np.float64))

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> Camera:
        """A PINHOLE camera from a (3, 3) matrix (cx, cy in our convention)."""
        K = np.asarray(K, dtype=np.float64)
        return cls.pinhole(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)
