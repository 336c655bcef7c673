"""Triangle meshes for scene objects: primitives, height-field terrain, user meshes.

Each object becomes a `PlacedMesh`: vertices/triangles in the object's local
frame plus its placement `x_world = R @ (s * x_local) + t`. Geometry is float64
here and float32 once handed to Embree (open3d `RaycastingScene`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from data_synth.noise import apply_affine, fbm
from data_synth.spec import ObjectSpec
from mvgeo.common.errors import InputError


@dataclass(frozen=True)
class PlacedMesh:
    """A triangle mesh and its placement.

    Attributes:
        name: the object's name.
        vertices_local: (V, 3) float64, object frame.
        triangles: (T, 3) int32 vertex indices, counter-clockwise seen from outside.
        normals_local: (V, 3) float64 unit vertex normals (used when `smooth`).
        R: (3, 3) world_from_local rotation; t: (3,) translation; scale: uniform scale.
        smooth: shade with interpolated vertex normals instead of face normals.
    """

    name: str
    vertices_local: np.ndarray
    triangles: np.ndarray
    normals_local: np.ndarray
    R: np.ndarray
    t: np.ndarray
    scale: float
    smooth: bool

    def vertices_world(self) -> np.ndarray:
        """(V, 3) float64 vertices in the world frame."""
        return (self.scale * self.vertices_local) @ self.R.T + self.t

    def normals_world(self) -> np.ndarray:
        """(V, 3) float64 unit vertex normals in the world frame (uniform scale keeps them normal)."""
        return self.normals_local @ self.R.T

    def local_from_world(self, points_world: np.ndarray) -> np.ndarray:
        """(M, 3) float32 world points -> (M, 3) float32 object-frame points."""
        Rinv = self.R.T / self.scale
        affine = np.hstack([Rinv, (-Rinv @ self.t)[:, None]])
        return apply_affine(points_world, affine.astype(np.float32))


def _plane(size: tuple[float, ...]) -> o3d.geometry.TriangleMesh:
    w, h = size
    v = np.array([[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]], float)
    tri = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(tri))


def _terrain(spec: ObjectSpec) -> o3d.geometry.TriangleMesh:
    w, h = spec.size
    n = int(spec.resolution)
    xs = np.linspace(-w / 2, w / 2, n + 1)
    ys = np.linspace(-h / 2, h / 2, n + 1)
    gx, gy = np.meshgrid(xs, ys)  # (n+1, n+1), row = y
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    z = fbm((pts / spec.feature_size).astype(np.float32), octaves=int(spec.octaves), seed=int(spec.seed))[:, 0]
    pts[:, 2] = spec.amplitude * z.astype(np.float64)
    idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    tri = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(pts), o3d.utility.Vector3iVector(tri.astype(np.int32)))


def load_user_mesh(path: Path) -> o3d.geometry.TriangleMesh:
    """Read a .ply/.obj triangle mesh with open3d.

    Raises:
        InputError: missing file, unsupported suffix, or no triangles.
    """
    if path.suffix.lower() not in (".ply", ".obj"):
        raise InputError(f"unsupported mesh format '{path.suffix}'", path=path, fix="use a .ply or .obj file")
    if not path.is_file():
        raise InputError("mesh file does not exist", path=path,
                         fix="mesh paths are relative to the scene file's folder")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0 or len(mesh.vertices) == 0:
        raise InputError("mesh has no triangles (corrupt or a point cloud)", path=path,
                         fix="export a triangle mesh")
    return mesh


def build_mesh(spec: ObjectSpec, *, base_dir: Path | None = None) -> PlacedMesh:
    """The triangle mesh of one object.

    Args:
        spec: a validated object spec.
        base_dir: folder that relative `mesh` paths are resolved against.
    """
    if spec.shape == "plane":
        mesh = _plane(spec.size)
    elif spec.shape == "box":
        sx, sy, sz = spec.size
        mesh = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
        mesh.translate((-sx / 2, -sy / 2, -sz / 2))
    elif spec.shape == "sphere":
        mesh = o3d.geometry.TriangleMesh.create_sphere(spec.radius, resolution=int(spec.resolution))
    elif spec.shape == "cylinder":
        mesh = o3d.geometry.TriangleMesh.create_cylinder(spec.radius, spec.height, resolution=int(spec.resolution),
                                                         split=1)
    elif spec.shape == "terrain":
        mesh = _terrain(spec)
    else:
        path = Path(spec.path)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        mesh = load_user_mesh(path)
    mesh.compute_vertex_normals()
    R = Rotation.from_euler("xyz", spec.rotate_deg, degrees=True).as_matrix()
    return PlacedMesh(
        name=spec.name,
        vertices_local=np.asarray(mesh.vertices, dtype=np.float64),
        triangles=np.asarray(mesh.triangles, dtype=np.int32),
        normals_local=np.asarray(mesh.vertex_normals, dtype=np.float64),
        R=R,
        t=np.asarray(spec.translate, dtype=np.float64),
        scale=float(spec.scale),
        smooth=bool(spec.smooth),
    )
