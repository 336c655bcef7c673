"""Ray-cast rendering of a scene with open3d's `RaycastingScene` (Embree, CPU).

Clean RGB is box-filtered over an n x n stratified grid of rays per pixel.
Depth (z in the camera frame, `inf` where the pixel-centre ray misses), alpha
(fraction of a pixel's rays that hit) and normals (camera frame, unit, on
the side of the surface the camera sees, decided by the face; zero where
nothing is hit) are computed only when asked.
Shading is Lambertian with one directional light and an ambient term (or
unlit): view-independent, so a surface point has the same colour in every view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c

from data_synth.geometry import PlacedMesh, build_mesh
from data_synth.intrinsics import camera_rays, sample_positions
from data_synth.spec import LightingSpec, SceneSpec, TextureSpec
from data_synth.textures import evaluate_texture
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError, check_shape


@dataclass(frozen=True)
class ViewRender:
    """What one view's render produced; fields not asked for are None.

    Attributes:
        rgb: (H, W, 3) float32 clean image in [0, 1].
        depth: (H, W) float32 z-depth of the pixel-centre ray, inf on a miss.
        alpha: (H, W) float32 coverage in [0, 1].
        normals: (H, W, 3) float32 unit normals in the camera frame (OpenCV axes), 0 on a miss.
    """

    rgb: np.ndarray
    depth: np.ndarray | None = None
    alpha: np.ndarray | None = None
    normals: np.ndarray | None = None


@dataclass(frozen=True)
class RayHits:
    """Per-ray results of one cast (M rays).

    Attributes:
        hit: (M,) bool; t: (M,) float32 ray parameter (z-depth for unit-z directions), inf on a miss;
        object_index: (M,) int64 (-1 on a miss); points_world: (M, 3) float32;
        normals_world: (M, 3) float32 unit shading normals on the side of the hit face that faces the ray
        origin (an interpolated normal at a grazing hit may point slightly away from it), 0 on a miss, or
        None when not computed.
    """

    hit: np.ndarray
    t: np.ndarray
    object_index: np.ndarray
    points_world: np.ndarray
    normals_world: np.ndarray | None


class SceneRenderer:
    """Holds the Embree scene, meshes, textures and lighting of one scene; renders views.

    Args:
        meshes: placed meshes (their order defines object indices).
        textures: one texture per mesh.
        lighting: shading model.
        background: RGB where rays miss.
    """

    def __init__(self, meshes: list[PlacedMesh], textures: list[TextureSpec], *, lighting: LightingSpec,
                 background: tuple[float, float, float]):
        if len(meshes) != len(textures):
            raise ValueError("one texture per mesh")
        self.meshes = meshes
        self.textures = textures
        self.lighting = lighting
        self.background = np.asarray(background, dtype=np.float32)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._vertex_normals_world: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        for k, mesh in enumerate(meshes):
            tmesh = o3d.t.geometry.TriangleMesh()
            tmesh.vertex.positions = o3c.Tensor(mesh.vertices_world().astype(np.float32))
            tmesh.triangle.indices = o3c.Tensor(mesh.triangles.astype(np.int32))
            gid = self._scene.add_triangles(tmesh)
            if gid != k:  # open3d numbers geometries 0, 1, ... in insertion order
                raise RuntimeError(f"unexpected open3d geometry id {gid} for object {k}")
            self._vertex_normals_world.append(mesh.normals_world().astype(np.float32))
            self._triangles.append(mesh.triangles)
        light = np.asarray(lighting.direction, dtype=np.float32)
        self._light_dir = light / np.linalg.norm(light)

    @classmethod
    def from_spec(cls, spec: SceneSpec) -> SceneRenderer:
        """Build meshes for every object of a resolved scene."""
        base_dir = spec.source.parent if isinstance(spec.source, Path) else None
        meshes = [build_mesh(obj, base_dir=base_dir) for obj in spec.objects]
        textures = [spec.textures[obj.texture] for obj in spec.objects]
        return cls(meshes, textures, lighting=spec.lighting, background=spec.render.background)

    # -- ray casting -----------------------------------------------------------------
    def cast(self, origins: np.ndarray, dirs: np.ndarray, *, normals: bool) -> RayHits:
        """Cast rays `origins + t * dirs`.

        Args:
            origins: (M, 3) or (3,) world-frame ray origins.
            dirs: (M, 3) world-frame directions (not necessarily unit; t is in their units).
            normals: also compute shading normals.
        """
        check_shape(dirs, ["M", 3], "dirs")
        dirs32 = np.asarray(dirs, dtype=np.float32)
        m = dirs32.shape[0]
        rays = np.empty((m, 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs32
        out = self._scene.cast_rays(o3c.Tensor(rays))
        t = out["t_hit"].numpy()
        hit = np.isfinite(t)
        gid = out["geometry_ids"].numpy().astype(np.int64)
        object_index = np.where(hit, gid, -1)
        points = rays[:, :3] + np.where(hit, t, 0)[:, None] * dirs32
        n_world = None
        if normals:
            n_world = out["primitive_normals"].numpy().astype(np.float32)
            # Two-sided surfaces: the side seen is decided by the face (geometric) normal. Deciding it
            # with the interpolated normal instead would turn that normal inwards where a grazing ray
            # sees a face whose vertex normals already point away (a smooth object's silhouette):
            # shading that depends on the view.
            seen_from_back = np.sum(n_world * dirs32, axis=1) > 0
            prim = out["primitive_ids"].numpy().astype(np.int64)
            uvs = out["primitive_uvs"].numpy()
            for k, mesh in enumerate(self.meshes):
                if not mesh.smooth:
                    continue
                sel = np.nonzero(object_index == k)[0]
                if sel.size == 0:
                    continue
                tri = self._triangles[k][prim[sel]]
                vn = self._vertex_normals_world[k]
                u, v = uvs[sel, 0:1], uvs[sel, 1:2]
                smooth = (1 - u - v) * vn[tri[:, 0]] + u * vn[tri[:, 1]] + v * vn[tri[:, 2]]
                # Keep the interpolated normal on the same side as the face normal.
                flip = np.sum(smooth * n_world[sel], axis=1) < 0
                smooth[flip] *= -1
                n_world[sel] = smooth / np.maximum(np.linalg.norm(smooth, axis=1, keepdims=True), 1e-12)
            n_world[seen_from_back] *= -1
            n_world[~hit] = 0
        return RayHits(hit=hit, t=t, object_index=object_index, points_world=points, normals_world=n_world)

    def shade(self, hits: RayHits) -> np.ndarray:
        """(M, 3) float32 colour of each ray (background on a miss)."""
        m = hits.hit.shape[0]
        rgb = np.empty((m, 3), dtype=np.float32)
        rgb[:] = self.background
        for k, mesh in enumerate(self.meshes):
            sel = np.nonzero(hits.object_index == k)[0]
            if sel.size == 0:
                continue
            albedo = evaluate_texture(self.textures[k], mesh.local_from_world(hits.points_world[sel]))
            if self.lighting.mode == "lambert":
                cos = np.maximum(hits.normals_world[sel] @ self._light_dir, 0)
                shading = np.float32(self.lighting.ambient) + np.float32(self.lighting.intensity) * cos
                albedo = albedo * shading[:, None]
            rgb[sel] = albedo
        return np.clip(rgb, 0.0, 1.0)

    # -- views ------------------------------------------------------------------------
    def render(self, camera: Camera, cam_from_world: np.ndarray, *, supersample: int = 2, depth: bool = False,
               alpha: bool = False, normals: bool = False) -> ViewRender:
        """Render one view.

        Args:
            camera: intrinsics (PINHOLE / OPENCV ...).
            cam_from_world: (3, 4) float64 pose.
            supersample: n, for n x n rays per pixel.
            depth, alpha, normals: compute these outputs too.
        """
        check_shape(cam_from_world, [3, 4], "cam_from_world")
        w, h = camera.width, camera.height
        n = int(supersample)
        R = np.asarray(cam_from_world[:, :3], dtype=np.float64)
        centre = -R.T @ np.asarray(cam_from_world[:, 3], dtype=np.float64)

        uv = sample_positions((w, h), n).reshape(-1, 2)
        dirs_cam, valid = camera_rays(camera, uv)
        need_normals = self.lighting.mode == "lambert" or (normals and n % 2 == 1)
        hits = self.cast(centre, dirs_cam @ R, normals=need_normals)
        hits = _drop(hits, ~valid)
        rgb = _box_filter(self.shade(hits).reshape(h, n, w, n, 3))
        out_alpha = _box_filter(hits.hit.astype(np.float32).reshape(h, n, w, n)) if alpha else None

        out_depth = out_normals = None
        if depth or normals:
            if n % 2 == 1:  # the centre sample of each pixel is the pixel-centre ray
                c = n // 2
                centre_t = hits.t.reshape(h, n, w, n)[:, c, :, c]
                centre_n = hits.normals_world.reshape(h, n, w, n, 3)[:, c, :, c] if normals else None
            else:
                uv_c = sample_positions((w, h), 1).reshape(-1, 2)
                dirs_c, valid_c = camera_rays(camera, uv_c)
                hc = _drop(self.cast(centre, dirs_c @ R, normals=normals), ~valid_c)
                centre_t = hc.t.reshape(h, w)
                centre_n = hc.normals_world.reshape(h, w, 3) if normals else None
            if depth:
                out_depth = np.where(np.isfinite(centre_t), centre_t, np.inf).astype(np.float32)
            if normals:
                out_normals = (centre_n.astype(np.float64) @ R.T).astype(np.float32)
        return ViewRender(rgb=rgb, depth=out_depth, alpha=out_alpha, normals=out_normals)


def _box_filter(samples: np.ndarray) -> np.ndarray:
    """Mean over the (i, j) sample axes of an (H, n, W, n, ...) array (sums of slices: fast)."""
    n = samples.shape[1]
    acc = np.zeros(samples.shape[:1] + samples.shape[2:3] + samples.shape[4:], dtype=np.float32)
    for i in range(n):
        for j in range(n):
            acc += samples[:, i, :, j]
    return acc * np.float32(1.0 / (n * n))


def _drop(hits: RayHits, invalid: np.ndarray) -> RayHits:
    """Mark rays outside the lens model's valid region as misses."""
    if not np.any(invalid):
        return hits
    hit = hits.hit & ~invalid
    t = np.where(hit, hits.t, np.float32(np.inf)).astype(np.float32)
    idx = np.where(hit, hits.object_index, -1)
    nw = None
    if hits.normals_world is not None:
        nw = hits.normals_world.copy()
        nw[~hit] = 0
    return RayHits(hit=hit, t=t, object_index=idx, points_world=hits.points_world, normals_world=nw)


# -- memory -------------------------------------------------------------------------------

#: Bytes per ray at the peak of `SceneRenderer.render` (the `n x n` rays of every pixel are cast in
#: one batch). Live at the end of `SceneRenderer.cast`: sample positions (2 float64 = 16), camera
#: rays and their valid flag (3 float64 + bool = 25), world rays (24), float32 rays and the 6-float
#: ray buffer for Open3D (12 + 24), Open3D's hit records (t, geometry and primitive ids, uv,
#: normal: 32), hit mask and object index (1 + 8), hit points (12), normals (12), primitive ids
#: (8): 182 B, plus short-lived temporaries. Measured peak RSS on `llff_like` (one view, 512x384 to
#: 2048x1536, supersample 1 to 3): 202 to 209 B per ray; tracemalloc (numpy's share only):
#: 167 B per ray.
RAY_BYTES = 224

#: Bytes per output pixel on top of the rays: the view's colour, depth, alpha and normal images
#: (12 + 4 + 4 + 12), the degraded copy the effects make (float64 working copies of the RGB image,
#: up to 6 x 24), the 16-bit PNG encodings (2 x 6) and the previous view's images, still held while
#: the next one renders (44).
PIXEL_BYTES = 256


def estimate_render_bytes(size_wh: tuple[int, int], supersample: int) -> int:
    """Peak memory of rendering one view (views render one after another), in bytes.

    ``RAY_BYTES * W * H * n**2 + PIXEL_BYTES * W * H`` for a ``W x H`` view with ``n x n`` rays per
    pixel. The scene's meshes and textures, built once before the first view, are not included
    (a few MiB for the built-in scenes).
    """
    w, h = (int(v) for v in size_wh)
    n = int(supersample)
    return RAY_BYTES * w * h * n * n + PIXEL_BYTES * w * h


def available_memory_bytes() -> int | None:
    """Memory this process can still allocate, in bytes, or None when it cannot be read.

    `MemAvailable` of ``/proc/meminfo``, lowered to the cgroup (v2) limit minus its usage when the
    process runs under one; ``psutil.virtual_memory().available`` where ``/proc/meminfo`` is
    missing (macOS, Windows) and psutil is installed.
    """
    avail = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                avail = int(line.split()[1]) * 1024
                break
    except OSError:
        avail = None
    if avail is None:
        try:
            import psutil
        except ImportError:
            return None
        return int(psutil.virtual_memory().available)
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            avail = min(avail, max(0, int(limit) - used))
    except (OSError, ValueError):
        pass
    return avail


def check_render_memory(spec: SceneSpec, *, available_bytes: int | None = None) -> int:
    """Refuse a render whose one-view peak (`estimate_render_bytes`) exceeds the available memory.

    Args:
        spec: the resolved scene (its ``render.size`` and ``render.supersample``).
        available_bytes: the limit; default `available_memory_bytes()` (no check when unknown).

    Returns:
        The estimate in bytes.

    Raises:
        InputError: quoting the estimate and the limit, with a size that would fit.
    """
    w, h = spec.render.size
    n = spec.render.supersample
    need = estimate_render_bytes((w, h), n)
    limit = available_memory_bytes() if available_bytes is None else available_bytes
    if limit is None or need <= limit:
        return need
    scale = math.sqrt(limit / need) if limit > 0 else 0.0
    fit_w, fit_h = int(w * scale), int(h * scale)
    hint = f"--size {fit_w}x{fit_h} or smaller" if min(fit_w, fit_h) >= 8 else "a much smaller --size"
    raise InputError(f"rendering one {w}x{h} view with {n}x{n} rays per pixel needs about "
                     f"{need / 2**30:.1f} GiB of memory ({RAY_BYTES} B per ray + {PIXEL_BYTES} B per pixel); "
                     f"{limit / 2**30:.1f} GiB is available",
                     fix=f"use {hint}, a lower [render] supersample, or free memory")
