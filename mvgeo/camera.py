"""Camera intrinsics (COLMAP camera models) — conventions in docs/conventions.md.

`Camera` holds a COLMAP model name, the image size and the parameters in
COLMAP's order, with the principal point in our pixel convention (the
top-left pixel's centre is (0.5, 0.5), as in COLMAP).

Projection model (all models, see `mvgeo.distortion`): ``x = X/Z, y = Y/Z``,
``(xd, yd) = distort(x, y)``, ``u = fx xd + cx``, ``v = fy yd + cy``.
Jacobian layout: ``d_uv_d_point (..., 2, 3)``, ``d_uv_d_params (..., 2, P)``
with columns in the model's COLMAP parameter order.

Interop (the 0.5 px shift is applied here and only here):
- OpenCV (`to_opencv`/`from_opencv`): ``K`` with ``cx - 0.5, cy - 0.5`` and
  the distortion vector ``[k1, k2, p1, p2(, k3, k4, k5, k6)]``.
- mrcal (`to_mrcal`/`from_mrcal`): ``LENSMODEL_PINHOLE`` / ``OPENCV4`` /
  ``OPENCV8`` intrinsics ``[fx, fy, cx - 0.5, cy - 0.5, ...]``.
- pycolmap (`to_pycolmap`/`from_pycolmap`): same parameters, no shift.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mvgeo.common.errors import InputError, check_shape
from mvgeo.distortion import distort, undistort

#: COLMAP model name -> parameter names, in COLMAP's order.
CAMERA_MODEL_PARAMS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


# Distortion coefficient -> index into the 8-vector [k1, k2, p1, p2, k3, k4, k5, k6] per model.
_DIST_INDEX: dict[str, tuple[int, ...]] = {
    "SIMPLE_PINHOLE": (),
    "PINHOLE": (),
    "SIMPLE_RADIAL": (0,),
    "OPENCV": (0, 1, 2, 3),
    "FULL_OPENCV": (0, 1, 2, 3, 4, 5, 6, 7),
}
_SINGLE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL")

#: mrcal lens model per COLMAP model (SIMPLE models map to the general one with fx = fy).
MRCAL_LENSMODEL: dict[str, str] = {
    "SIMPLE_PINHOLE": "LENSMODEL_PINHOLE",
    "PINHOLE": "LENSMODEL_PINHOLE",
    "SIMPLE_RADIAL": "LENSMODEL_OPENCV4",
    "OPENCV": "LENSMODEL_OPENCV4",
    "FULL_OPENCV": "LENSMODEL_OPENCV8",
}


@dataclass(frozen=True)
class Projection:
    """Result of `Camera.project`.

    Attributes:
        uv_px: (..., 2) pixel coordinates (our convention); finite everywhere,
            meaningless where ``valid`` is False.
        valid: (...) bool: ``Z > 0`` and inside the lens model's valid
            (monotonic) region. Being inside the image is *not* required; see
            `Camera.in_image`.
        d_uv_d_point: (..., 2, 3) or None.
        d_uv_d_params: (..., 2, P) or None, columns in COLMAP parameter order.
    """

    uv_px: np.ndarray
    valid: np.ndarray
    d_uv_d_point: np.ndarray | None = None
    d_uv_d_params: np.ndarray | None = None


@dataclass(frozen=True)
class Unprojection:
    """Result of `Camera.unproject`.

    Attributes:
        rays_cam: (..., 3) ray directions ``[x, y, 1]`` (z = 1, not unit length).
        valid: (...) bool: the undistortion converged and the solution lies in
            the lens model's valid region.
        converged: (...) bool: the Newton iteration reached its tolerance.
        residual_px: (...) reprojection residual of the returned ray, pixels.
    """

    rays_cam: np.ndarray
    valid: np.ndarray
    converged: np.ndarray
    residual_px: np.ndarray


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

    def pinhole_problem(self) -> str | None:
        """Why this camera is not a pinhole the splat can render, in words, or None: a focal length that
        is not positive and finite, or lens distortion (a distortion coefficient not zero)."""
        if not (np.isfinite(self.fx) and np.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            return f"its focal length is not positive (fx {self.fx:g}, fy {self.fy:g} px)"
        coefficients = self.params[3 if self.model in _SINGLE_FOCAL else 4:]
        if np.any(coefficients != 0.0):
            return (f"it has lens distortion ({self.model} {coefficients.tolist()}); the splat renders pinhole "
                    "cameras")
        return None

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

    # -- distortion ---------------------------------------------------------
    @property
    def dist(self) -> np.ndarray:
        """(8,) ``[k1, k2, p1, p2, k3, k4, k5, k6]`` (zeros for the coefficients the model lacks)."""
        d = np.zeros(8)
        n_pinhole = 3 if self.model in _SINGLE_FOCAL else 4
        d[list(_DIST_INDEX[self.model])] = self.params[n_pinhole:]
        return d

    # -- projection ---------------------------------------------------------
    def project(self, points_cam, *, with_jacobians: bool = False) -> Projection:
        """Project camera-frame points to pixels.

        Args:
            points_cam: (..., 3) points in the camera frame (OpenCV axes).
            with_jacobians: also return ``d uv / d point`` and ``d uv / d params``.

        Returns:
            `Projection` (float64).
        """
        P = np.asarray(points_cam, dtype=np.float64)
        check_shape(P, ["*", 3], "points_cam")
        Z = P[..., 2]
        in_front = Z > 0
        Z_safe = np.where(in_front, Z, 1.0)
        xy = P[..., :2] / Z_safe[..., None]
        d = distort(xy, self.dist)
        f = np.array([self.fx, self.fy])
        uv = d.xy_dist * f + np.array([self.cx, self.cy])
        valid = in_front & d.valid & np.all(np.isfinite(P), axis=-1)
        uv = np.where(np.isfinite(uv), uv, 0.0)
        if not with_jacobians:
            return Projection(uv_px=uv, valid=valid)
        # d xy / d P = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
        d_xy_d_P = np.zeros(P.shape[:-1] + (2, 3))
        d_xy_d_P[..., 0, 0] = 1 / Z_safe
        d_xy_d_P[..., 1, 1] = 1 / Z_safe
        d_xy_d_P[..., :, 2] = -xy / Z_safe[..., None]
        d_uv_d_point = f[:, None] * (d.d_xy @ d_xy_d_P)
        n_pin = 3 if self.model in _SINGLE_FOCAL else 4
        J = np.zeros(P.shape[:-1] + (2, self.params.size))
        if self.model in _SINGLE_FOCAL:
            J[..., :, 0] = d.xy_dist
            J[..., 0, 1] = 1.0
            J[..., 1, 2] = 1.0
        else:
            J[..., 0, 0] = d.xy_dist[..., 0]
            J[..., 1, 1] = d.xy_dist[..., 1]
            J[..., 0, 2] = 1.0
            J[..., 1, 3] = 1.0
        J[..., n_pin:] = f[:, None] * d.d_dist[..., list(_DIST_INDEX[self.model])]
        return Projection(uv_px=uv, valid=valid, d_uv_d_point=d_uv_d_point, d_uv_d_params=J)

    def unproject(self, uv_px, *, tol_px: float = 1e-9, max_iterations: int = 50) -> Unprojection:
        """Back-project pixels to camera-frame rays ``[x, y, 1]``.

        Distortion is inverted by damped Newton iterations (`mvgeo.distortion.undistort`)
        with a convergence check; pixels whose undistortion does not converge,
        or converges outside the model's valid region, are flagged invalid.

        Args:
            uv_px: (..., 2) pixel coordinates (our convention).
            tol_px: convergence tolerance in pixels.
            max_iterations: Newton iterations.

        Returns:
            `Unprojection` (float64).
        """
        uv = np.asarray(uv_px, dtype=np.float64)
        check_shape(uv, ["*", 2], "uv_px")
        f = np.array([self.fx, self.fy])
        xy_d = (uv - np.array([self.cx, self.cy])) / f
        tol = tol_px / float(np.max(np.abs(f)))
        u = undistort(xy_d, self.dist, tol=tol, max_iterations=max_iterations)
        rays = np.concatenate([u.xy, np.ones(u.xy.shape[:-1] + (1,))], axis=-1)
        residual_px = u.residual * float(np.max(np.abs(f)))
        return Unprojection(rays_cam=rays, valid=u.valid, converged=u.converged, residual_px=residual_px)

    def in_image(self, uv_px) -> np.ndarray:
        """(...) bool: ``0 <= u <= width`` and ``0 <= v <= height`` for uv (..., 2)."""
        uv = np.asarray(uv_px, dtype=np.float64)
        return (uv[..., 0] >= 0) & (uv[..., 0] <= self.width) & (uv[..., 1] >= 0) & (uv[..., 1] <= self.height)

    # -- resizing -----------------------------------------------------------
    def scaled(self, width: int, height: int) -> Camera:
        """The same lens for an image resized to ``width x height``.

        In our pixel convention the image spans ``[0, W]``, so every pixel
        quantity scales exactly by ``W'/W`` (x) and ``H'/H`` (y); distortion
        acts on normalised coordinates and is unchanged. A single-focal model
        whose aspect changes becomes PINHOLE / OPENCV (fx != fy).
        """
        if int(width) <= 0 or int(height) <= 0:
            raise InputError(f"scaled: size must be positive, got {width}x{height}")
        sx = int(width) / self.width
        sy = int(height) / self.height
        fx, fy, cx, cy = self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy
        dist_params = self.params[3 if self.model in _SINGLE_FOCAL else 4:]
        if self.model in _SINGLE_FOCAL and sx == sy:
            params = np.r_[fx, cx, cy, dist_params]
            return Camera(self.model, int(width), int(height), params)
        model = {"SIMPLE_PINHOLE": "PINHOLE", "SIMPLE_RADIAL": "OPENCV"}.get(self.model, self.model)
        if model == "OPENCV" and self.model == "SIMPLE_RADIAL":
            dist_params = np.r_[dist_params, 0.0, 0.0, 0.0]
        return Camera(model, int(width), int(height), np.r_[fx, fy, cx, cy, dist_params])

    # -- interop ------------------------------------------------------------
    def to_opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """``(K_cv (3, 3), dist_cv (N,))`` for cv2 functions (top-left pixel centre at (0, 0)).

        ``dist_cv`` has 4 entries for SIMPLE_RADIAL/OPENCV, 8 for FULL_OPENCV, 0 for pinholes.
        """
        K = self.K.copy()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        n = {0: 0, 1: 4, 4: 4, 8: 8}[len(_DIST_INDEX[self.model])]
        return K, self.dist[:n].copy()

    @classmethod
    def from_opencv(cls, K_cv, dist_cv, width: int, height: int) -> Camera:
        """Inverse of `to_opencv`: PINHOLE (no dist), OPENCV (4/5 coeffs with k3 = 0) or FULL_OPENCV (5/8)."""
        K = np.asarray(K_cv, dtype=np.float64)
        check_shape(K, [3, 3], "K_cv")
        d = np.asarray(dist_cv, dtype=np.float64).ravel()
        pin = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
        if d.size == 0 or not np.any(d):
            return cls("PINHOLE", width, height, np.array(pin))
        if d.size not in (4, 5, 8):
            raise InputError(f"OpenCV distortion with {d.size} coefficients is not supported",
                             fix="use 4, 5 or 8 coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]])")
        d8 = np.zeros(8)
        d8[: d.size] = d
        if not np.any(d8[4:]):
            return cls("OPENCV", width, height, np.r_[pin, d8[:4]])
        return cls("FULL_OPENCV", width, height, np.r_[pin, d8])

    def to_mrcal(self) -> tuple[str, np.ndarray]:
        """``(lensmodel, intrinsics)`` for mrcal (principal point shifted by -0.5 px)."""
        lens = MRCAL_LENSMODEL[self.model]
        pin = np.array([self.fx, self.fy, self.cx - 0.5, self.cy - 0.5])
        d = self.dist
        extra = {"LENSMODEL_PINHOLE": d[:0], "LENSMODEL_OPENCV4": d[:4], "LENSMODEL_OPENCV8": d}[lens]
        return lens, np.r_[pin, extra]

    @classmethod
    def from_mrcal(cls, lensmodel: str, intrinsics, width: int, height: int) -> Camera:
        """Camera from an mrcal lens model (PINHOLE, OPENCV4, OPENCV5, OPENCV8)."""
        intr = np.asarray(intrinsics, dtype=np.float64).ravel()
        sizes = {"LENSMODEL_PINHOLE": 4, "LENSMODEL_OPENCV4": 8, "LENSMODEL_OPENCV5": 9, "LENSMODEL_OPENCV8": 12}
        if lensmodel not in sizes:
            raise InputError(f"mrcal lens model {lensmodel!r} has no COLMAP equivalent here",
                             fix=f"use one of {', '.join(sizes)}")
        if intr.size != sizes[lensmodel]:
            raise InputError(f"{lensmodel} takes {sizes[lensmodel]} intrinsics, got {intr.size}")
        pin = np.r_[intr[:2], intr[2:4] + 0.5]
        if lensmodel == "LENSMODEL_PINHOLE":
            return cls("PINHOLE", width, height, pin)
        if lensmodel == "LENSMODEL_OPENCV4":
            return cls("OPENCV", width, height, np.r_[pin, intr[4:]])
        d8 = np.zeros(8)
        d8[: intr.size - 4] = intr[4:]
        return cls("FULL_OPENCV", width, height, np.r_[pin, d8])

    def to_pycolmap(self):
        """A `pycolmap.Camera` with the same model and parameters (same pixel convention)."""
        from mvgeo.common.deps import pycolmap

        return pycolmap.Camera(model=self.model, width=self.width, height=self.height, params=self.params.copy())

    @classmethod
    def from_pycolmap(cls, cam) -> Camera:
        """Camera from a `pycolmap.Camera` (supported models only)."""
        return cls(cam.model.name, int(cam.width), int(cam.height), np.asarray(cam.params, dtype=np.float64))
