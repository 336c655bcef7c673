"""Slow, obviously-correct dense renderer: every Gaussian against every pixel.

Written independently of `splat/` (no shared helpers except the SH basis, which
has its own test) so that agreement means something. Sequential
front-to-back loop over globally depth-sorted Gaussians, vectorised over
pixels, float64 by default. Memory O(H W), time O(N H W).
"""

from __future__ import annotations

import torch

from splat.sh import eval_sh


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) wxyz (any norm) -> (N, 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def render_dense(means, quats, scales, opacities, colors, cam_from_world, K, width, height, *,
                 sh_degree=None, background=None, near_plane=0.01, far_plane=1e10, eps2d=0.3,
                 antialiased=False):
    """Returns rgb [3, H, W], alpha [1, H, W], depth [1, H, W] (same meaning as `splat.rasterize`)."""
    dtype = means.dtype
    R = cam_from_world[:3, :3]
    t = cam_from_world[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if sh_degree is not None:
        centre = -(R.T @ t)
        rgb_all = torch.clamp_min(eval_sh(sh_degree, colors, means - centre) + 0.5, 0.0)
    else:
        rgb_all = colors

    rows = torch.arange(height, dtype=dtype) + 0.5  # pixel centres, top-left at (0.5, 0.5)
    cols = torch.arange(width, dtype=dtype) + 0.5
    py, px = torch.meshgrid(rows, cols, indexing="ij")

    p_cam = means @ R.T + t
    order = torch.argsort(p_cam[:, 2].detach(), stable=True)
    T = torch.ones(height, width, dtype=dtype)
    done = torch.zeros(height, width, dtype=torch.bool)
    rgb = torch.zeros(3, height, width, dtype=dtype)
    depth_acc = torch.zeros(height, width, dtype=dtype)
    for i in order.tolist():
        x, y, z = p_cam[i]
        if not (near_plane < z.item() < far_plane):
            continue
        u = fx * x / z + cx
        v = fy * y / z + cy
        Rg = quat_to_matrix(quats[i:i + 1])[0]
        cov_world = Rg @ torch.diag(scales[i] ** 2) @ Rg.T
        cov_cam = R @ cov_world @ R.T
        # Jacobian of (fx x/z + cx, fy y/z + cy) at a point whose x/z, y/z are clamped to the
        # image's field of view widened by 0.3 * tan(half fov) (gsplat's rule).
        lim_x = ((width - cx) / fx + 0.15 * width / fx, cx / fx + 0.15 * width / fx)
        lim_y = ((height - cy) / fy + 0.15 * height / fy, cy / fy + 0.15 * height / fy)
        xz = torch.clamp(x / z, min=-lim_x[1], max=lim_x[0])
        yz = torch.clamp(y / z, min=-lim_y[1], max=lim_y[0])
        zero = torch.zeros((), dtype=dtype)
        J = torch.stack([
            torch.stack([fx / z, zero, -fx * xz / z]),
            torch.stack([zero, fy / z, -fy * yz / z]),
        ])
        cov2d_raw = J @ cov_cam @ J.T
        cov2d = cov2d_raw + eps2d * torch.eye(2, dtype=dtype)
        if torch.linalg.det(cov2d).item() <= 0:
            continue
        inv = torch.linalg.inv(cov2d)
        o = opacities[i]
        if antialiased:
            o = o * torch.sqrt(torch.clamp(torch.linalg.det(cov2d_raw) / torch.linalg.det(cov2d), min=0.0))
        dx = u - px
        dy = v - py
        sigma = 0.5 * (inv[0, 0] * dx * dx + inv[1, 1] * dy * dy) + inv[0, 1] * dx * dy
        alpha = torch.clamp(o * torch.exp(-torch.clamp(sigma, min=0.0)), max=0.99)
        use = (~done) & (sigma >= 0) & (alpha >= 1.0 / 255.0)
        next_T = T * (1 - alpha)
        stop = use & (next_T <= 1e-4)
        done = done | stop
        use = use & ~stop
        w = torch.where(use, alpha * T, torch.zeros_like(alpha))
        rgb = rgb + w[None] * rgb_all[i][:, None, None]
        depth_acc = depth_acc + w * z
        T = torch.where(use, next_T, T)
    alpha_img = 1 - T
    if background is not None:
        rgb = rgb + T[None] * background[:, None, None]
    depth = depth_acc / torch.clamp(alpha_img, min=1e-10)
    return rgb, alpha_img[None], depth[None]
