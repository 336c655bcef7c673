"""Synthetic pairwise pointmaps from known geometry (a sphere in front of a plane)."""

from __future__ import annotations

import numpy as np

from mvgeo.align.global_align import pixel_rays
from mvgeo.align.pairs import PairGeometry, PairPrediction, PairSet

SPHERE_C = np.array([0.0, 0.0, 4.0])
SPHERE_R = 1.0
PLANE_Z = 6.0


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(3, 4) cam_from_world for a camera at `centre` looking at `target` (y roughly down)."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)  # OpenCV: y down, so x = y_down x z... keep right-handed
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return np.concatenate([R, (-R @ centre).reshape(3, 1)], axis=1)


def render_depth(cam_from_world: np.ndarray, H: int, W: int, focal: float) -> np.ndarray:
    """(H, W) z-depth of the sphere-and-plane scene."""
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    C = -R.T @ t
    rays_cam = pixel_rays(H, W, focal)  # z = 1
    d = rays_cam @ R  # world directions (R^T ray), z-depth parametrisation: x = C + s * d, s = z-depth
    # plane z_world = PLANE_Z
    s_plane = (PLANE_Z - C[2]) / d[..., 2]
    # sphere |C + s d - Sc|^2 = r^2
    oc = C - SPHERE_C
    a = np.sum(d * d, axis=-1)
    b = 2 * d @ oc
    c = oc @ oc - SPHERE_R**2
    disc = b * b - 4 * a * c
    s_sph = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    return np.minimum(np.where(s_plane > 0, s_plane, np.inf), np.where(s_sph > 0, s_sph, np.inf))


def make_views(n: int, *, H: int = 24, W: int = 32, focal: float = 30.0, radius: float = 0.8):
    """n cameras on an arc looking at the sphere. Returns (cam_from_world (n,3,4), depths)."""
    poses, depths = [], []
    for k in range(n):
        a = -0.5 + k / max(n - 1, 1)
        centre = np.array([radius * np.sin(a), 0.3 * np.cos(3 * a), 4.0 - 4.0 * np.cos(a) - 0.2 * k / n])
        centre[2] = 0.0 + 0.3 * np.sin(2 * a)
        poses.append(look_at(centre, SPHERE_C + np.array([0.1 * a, -0.05, 0.0])))
        depths.append(render_depth(poses[-1], H, W, focal))
    return np.stack(poses), depths


def make_pairs(poses, depths, focal: float, rng: np.random.Generator, *, noise: float = 0.0,
               focal_err: float = 0.0, pairs=None) -> list[PairPrediction]:
    """Exact (or noisy) pairwise pointmaps in camera i's frame at a random scale per pair."""
    n = len(poses)
    H, W = depths[0].shape
    pairs = pairs or [(i, j) for i in range(n) for j in range(i + 1, n)]
    out = []
    for i, j in pairs:
        s = float(np.exp(rng.normal(0, 0.5)))
        pts = []
        for v in (i, j):
            x_cam = pixel_rays(H, W, focal) * depths[v][..., None]
            Rv, tv = poses[v][:, :3], poses[v][:, 3]
            x_w = (x_cam - tv) @ Rv
            x_i = x_w @ poses[i][:, :3].T + poses[i][:, 3]
            x_i = x_i + noise * rng.normal(size=x_i.shape) * np.linalg.norm(x_i, axis=-1, keepdims=True)
            pts.append((s * x_i).astype(np.float32))
        conf = [(1.5 + 3 * rng.random((H, W))).astype(np.float32) for _ in range(2)]
        f_est = focal * (1 + focal_err * rng.normal())
        out.append(PairPrediction(i, j, pts[0], pts[1], conf[0], conf[1], f_est, f_est))
    return out


def make_matches(poses, depths, focal: float, pairs, *, step: int = 2) -> list[tuple[int, int, np.ndarray]]:
    """Exact matches `(i, j, (M, 4) (u_i, v_i, u_j, v_j))` in the depth maps' pixels: every `step`-th pixel of
    view i projected into view j, where it is inside and not occluded (view j's depth agrees within 1 %)."""
    H, W = depths[0].shape
    v, u = np.mgrid[0:H:step, 0:W:step] + 0.5
    out = []
    for i, j in pairs:
        z = depths[i][v.astype(int), u.astype(int)]
        x_cam = np.stack([(u - W / 2) / focal * z, (v - H / 2) / focal * z, z], -1).reshape(-1, 3)
        x_w = (x_cam - poses[i][:, 3]) @ poses[i][:, :3]
        x_j = x_w @ poses[j][:, :3].T + poses[j][:, 3]
        uv_j = x_j[:, :2] / x_j[:, 2:] * focal + np.array([W / 2, H / 2])
        inside = (x_j[:, 2] > 0) & np.all((uv_j >= 0) & (uv_j < [W, H]), axis=1)
        z_j = np.full(len(uv_j), np.nan)
        z_j[inside] = depths[j][uv_j[inside, 1].astype(int), uv_j[inside, 0].astype(int)]
        seen = inside & (np.abs(x_j[:, 2] / z_j - 1.0) < 0.01)
        out.append((i, j, np.concatenate([np.stack([u.ravel(), v.ravel()], 1)[seen], uv_j[seen]], axis=1)))
    return out


class PairSetModel:
    """A `PointmapModel` that returns precomputed pointmaps (and, where given, matches as verified pairs)."""

    pointmap_size_px = 32

    def __init__(self, preds, matches=(), *, focal_determined: bool = True):
        self.preds, self.matches, self.focal_determined = list(preds), list(matches), focal_determined

    def predict_pairs(self, images, pairs) -> PairSet:
        geos = [PairGeometry(i, j, np.asarray(uv, float)) for i, j, uv in self.matches]
        return PairSet(list(self.preds), [], geos, focal_determined=self.focal_determined)


def three_view_matches(rng: np.random.Generator, *, W: int = 320, H: int = 240, f: float = 300.0):
    """Three cameras 0.5 apart along x, turned 0.1 rad about y each, seeing 80 points 4-6 units ahead: (poses
    (3, 3, 4) cam_from_world, exact matches [(i, j, (80, 4))] of the three pairs)."""
    from mvgeo.transforms import so3_exp

    X = rng.uniform([-1, -1, 4], [1, 1, 6], (80, 3))
    poses = np.stack([np.concatenate([so3_exp(np.array([0, 0.1 * k, 0])), np.array([[-0.5 * k], [0], [0]])], 1)
                      for k in range(3)])
    uv = []
    for P in poses:
        xc = X @ P[:, :3].T + P[:, 3]
        uv.append(f * xc[:, :2] / xc[:, 2:] + [W / 2, H / 2])
    return poses, [(i, j, np.concatenate([uv[i], uv[j]], 1)) for i, j in ((0, 1), (0, 2), (1, 2))]
