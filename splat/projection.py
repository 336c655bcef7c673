"""Projection of 3D Gaussians to screen-space 2D Gaussians (EWA splatting).

Follows 3DGS / gsplat (docs/conventions.md): OpenCV pinhole `K` with the
top-left pixel centre at (0.5, 0.5), `cam_from_world` world-to-camera, wxyz
quaternions. Plain torch, differentiable with respect to every input
(means, quaternions, scales, opacities, the pose and `K`) by autograd; cost
and memory are O(N).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mvgeo.common.errors import check_shape
from mvgeo.transforms_torch import R_from_quat

#: Contributions with alpha below this are skipped by the compositor (3DGS/gsplat).
ALPHA_MIN = 1.0 / 255.0


@dataclass
class ProjectedGaussians:
    """Screen-space Gaussians of one view.

    Attributes:
        means2d: (N, 2) pixel coordinates (u, v), our pixel convention.
        conics: (N, 3) upper triangle (a, b, c) of the inverse 2D covariance.
        depths: (N,) z of the mean in the camera frame.
        opacities: (N,) opacities used for compositing (times the antialiasing
            compensation when enabled).
        extents_px: (N, 2) half-widths (x, y) of the axis-aligned box outside
            which alpha < 1/255 (no gradient); 0 for culled Gaussians.
        visible: (N,) bool, in front of the near plane, inside the far plane,
            alpha >= 1/255 somewhere, and the box overlaps the image.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    extents_px: torch.Tensor
    visible: torch.Tensor


def covariance_from_scale_rot(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World covariance `R S S^T R^T`.

    Args:
        quats: (N, 4) wxyz, any norm (normalised here).
        scales: (N, 3) standard deviations along the local axes (> 0).

    Returns:
        (N, 3, 3) covariances.
    """
    R = R_from_quat(torch.nn.functional.normalize(quats, dim=-1))
    M = R * scales[..., None, :]
    return M @ M.transpose(-1, -2)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    cam_from_world: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    antialiased: bool = False,
) -> ProjectedGaussians:
    """Project Gaussians into one pinhole view.

    The 2D covariance is `J W Sigma W^T J^T + eps2d * I` with the EWA Jacobian
    `J` evaluated at the mean, whose x/z and y/z are clamped to 0.3 * tan(fov)
    beyond the image border as gsplat does (keeps far-off-axis Gaussians from
    exploding). `eps2d` is the 0.3 px low-pass of 3DGS; `antialiased=True`
    multiplies opacity by `sqrt(det(Sigma2d) / det(Sigma2d + eps2d I))`
    (Mip-Splatting, gsplat's `rasterize_mode="antialiased"`).

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) wxyz rotations (normalised here).
        scales: (N, 3) activated scales (standard deviations).
        opacities: (N,) activated opacities in [0, 1].
        cam_from_world: (3, 4) or (4, 4) world-to-camera transform.
        K: (3, 3) pinhole intrinsics.
        width, height: image size in pixels.
        near_plane, far_plane: z range kept (camera frame units).
        eps2d: screen-space dilation in px^2.
        antialiased: opacity compensation for the dilation.

    Returns:
        `ProjectedGaussians`; culled Gaussians have `visible = False` and are
        ignored by the compositor (their values are finite but meaningless).
    """
    check_shape(means, ["N", 3], "means")
    n = means.shape[0]
    check_shape(quats, [n, 4], "quats")
    check_shape(scales, [n, 3], "scales")
    check_shape(opacities, [n], "opacities")
    check_shape(K, [3, 3], "K")
    if tuple(cam_from_world.shape) not in ((3, 4), (4, 4)):
        check_shape(cam_from_world, [3, 4], "cam_from_world")
    R_cw = cam_from_world[:3, :3]
    t_cw = cam_from_world[:3, 3]
    p_cam = means @ R_cw.T + t_cw
    x, y, z = p_cam.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    # Culled Gaussians get a safe z so nothing below produces inf/nan (also in gradients).
    z_safe = torch.where(in_depth, z, torch.ones_like(z))

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * x / z_safe + cx
    v = fy * y / z_safe + cy
    means2d = torch.stack([u, v], -1)

    # Sigma2d = J R_cw R S S R^T R_cw^T J^T = T T^T with T = J R_cw R S (2 x 3 per Gaussian). Written
    # as one (3, 3) x (3, 3N) matmul plus elementwise products: batched 3x3 bmm is slow on CPU.
    R = R_from_quat(torch.nn.functional.normalize(quats, dim=-1))
    M = R * scales[..., None, :]  # R S, (N, 3, 3)
    rows = (R_cw @ M.permute(1, 0, 2).reshape(3, 3 * n)).reshape(3, n, 3)  # rows[i] = row i of R_cw R S

    # gsplat's clamping of the Jacobian's evaluation point (not of the mean itself).
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    tx = z_safe * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x / z_safe))
    ty = z_safe * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y / z_safe))
    inv_z = 1.0 / z_safe
    # EWA Jacobian J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]] applied row by row.
    T0 = (fx * inv_z)[:, None] * rows[0] - (fx * tx * inv_z * inv_z)[:, None] * rows[2]
    T1 = (fy * inv_z)[:, None] * rows[1] - (fy * ty * inv_z * inv_z)[:, None] * rows[2]
    a0, b, c0 = (T0 * T0).sum(-1), (T0 * T1).sum(-1), (T1 * T1).sum(-1)
    det_orig = a0 * c0 - b * b
    a = a0 + eps2d
    c = c0 + eps2d
    det = a * c - b * b
    ok_det = det > 0
    det_safe = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], -1)

    if antialiased:
        comp = torch.sqrt(torch.clamp(det_orig / det_safe, min=0.0))
        opac = opacities * comp
    else:
        opac = opacities

    # Box outside which alpha = opac * exp(-0.5 d^T Sigma^-1 d) < 1/255:
    # Mahalanobis radius r^2 = 2 log(opac * 255); axis extents r * sqrt(Sigma_xx), r * sqrt(Sigma_yy).
    with torch.no_grad():
        r2 = 2.0 * torch.log(torch.clamp(opac.detach(), min=1e-30) / ALPHA_MIN)
        has_alpha = r2 > 0
        r = torch.sqrt(torch.clamp(r2, min=0.0))
        ext_x = r * torch.sqrt(torch.clamp(a.detach(), min=0.0))
        ext_y = r * torch.sqrt(torch.clamp(c.detach(), min=0.0))
        ud, vd = u.detach(), v.detach()
        on_image = (ud + ext_x > 0) & (ud - ext_x < width) & (vd + ext_y > 0) & (vd - ext_y < height)
        finite = torch.isfinite(ud) & torch.isfinite(vd) & torch.isfinite(ext_x) & torch.isfinite(ext_y)
        visible = in_depth & ok_det & has_alpha & on_image & finite
        extents = torch.where(visible[:, None], torch.stack([ext_x, ext_y], -1), torch.zeros_like(means2d))
    return ProjectedGaussians(
        means2d=means2d, conics=conics, depths=z, opacities=opac, extents_px=extents, visible=visible
    )

