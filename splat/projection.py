"""Projection of 3D Gaussians to screen-space 2D Gaussians (EWA splatting).

Follows 3DGS / gsplat (docs/conventions.md): OpenCV pinhole `K` with the
top-left pixel centre at (0.5, 0.5), `cam_from_world` world-to-camera, wxyz
quaternions. Differentiable with respect to every input (means, quaternions,
scales, opacities, the pose and `K`); cost and memory are O(N).

Two implementations of `project_gaussians`:

- `"torch"`: plain torch, autograd for the backward; any device. The reference.
- `"cpp"`: the C++ kernel `csrc/projection.cpp` with a hand-written backward (the
  chain rule of the same expressions), CPU, float32/float64.

`"auto"` picks `"cpp"` for CPU tensors when the kernels build, else `"torch"`
(one warning per process says why, `splat._cpu_kernel.available`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mvgeo.common.errors import check_shape
from mvgeo.transforms_torch import R_from_quat
from splat import _cpu_kernel

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


def resolve_backend(backend: str, device: torch.device) -> str:
    """"auto" -> "cpp" on CPU when the C++ kernels load (else "torch"); "torch"/"cpp" as given.

    Raises:
        ValueError: an unknown name, or "cpp" for tensors that are not on the CPU.
    """
    if backend == "auto":
        return "cpp" if (device.type == "cpu" and _cpu_kernel.available()) else "torch"
    if backend == "cpp":
        if device.type != "cpu":
            raise ValueError("the cpp kernels run on CPU tensors only; use backend='torch' on CUDA")
        return backend
    if backend == "torch":
        return backend
    raise ValueError(f"unknown splat backend {backend!r} (use 'auto', 'torch' or 'cpp')")


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
    backend: str = "torch",
    num_threads: int | None = None,
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
        backend: "torch" (the reference), "cpp" or "auto" (see the module docstring).
        num_threads: threads of the C++ kernel (default `torch.get_num_threads()`); the
            result does not depend on it. Ignored by the torch path.

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
    if resolve_backend(backend, means.device) == "cpp":
        return _project_cpp(means, quats, scales, opacities, cam_from_world, K, width, height, near_plane=near_plane,
                            far_plane=far_plane, eps2d=eps2d, antialiased=antialiased, num_threads=num_threads)
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
    # The 2D covariance, its determinant and inverse in float64, rounded once (as csrc/projection.cpp does):
    # det = a c - b^2 = |T0 x T1|^2 + ... is tiny next to a c for a thin Gaussian, and in float32 the
    # difference lost every digit for needles ~100 px long and sub-pixel thin (their antialiased opacity
    # off by up to 100 %, some culled; tests/splat/test_tiles_projection.py).
    T0d, T1d = T0.double(), T1.double()
    a0, b, c0 = (T0d * T0d).sum(-1), (T0d * T1d).sum(-1), (T1d * T1d).sum(-1)
    det_orig = a0 * c0 - b * b
    a = a0 + eps2d
    c = c0 + eps2d
    det = a * c - b * b
    ok_det = det > 0
    det_safe = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], -1).to(means.dtype)
    a, c = a.to(means.dtype), c.to(means.dtype)

    if antialiased:
        comp = torch.sqrt(torch.clamp(det_orig / det_safe, min=0.0)).to(opacities.dtype)
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


def _project_cpp(means, quats, scales, opacities, cam_from_world, K, width, height, *, near_plane, far_plane, eps2d,
                 antialiased, num_threads) -> ProjectedGaussians:
    options = {"width": int(width), "height": int(height), "near_plane": float(near_plane),
               "far_plane": float(far_plane), "eps2d": float(eps2d), "antialiased": bool(antialiased),
               "num_threads": num_threads}
    means2d, conics, depths, opac, extents, visible = _ProjectCpp.apply(
        means, quats, scales, opacities, cam_from_world, K, options)
    return ProjectedGaussians(means2d=means2d, conics=conics, depths=depths, opacities=opac, extents_px=extents,
                              visible=visible.bool())


class _ProjectCpp(torch.autograd.Function):
    """`csrc/projection.cpp` forward and backward; the computation runs in `means.dtype`."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, cam_from_world, K, options):
        dt = means.dtype
        tensors = [t.detach().to(dt).contiguous() for t in (means, quats, scales, opacities)]
        cam = cam_from_world.detach()[:3].to(dt).contiguous()
        K_c = K.detach().to(dt).contiguous()
        out = _cpu_kernel.project_forward(
            *tensors, cam, K_c, options["width"], options["height"], near_plane=options["near_plane"],
            far_plane=options["far_plane"], eps2d=options["eps2d"], antialiased=options["antialiased"],
            alpha_min=ALPHA_MIN, num_threads=options["num_threads"])
        ctx.save_for_backward(*tensors, cam, K_c)
        ctx.options = options
        ctx.in_dtypes = [t.dtype for t in (means, quats, scales, opacities, cam_from_world, K)]
        ctx.cam_rows = cam_from_world.shape[0]
        ctx.mark_non_differentiable(out[4], out[5])
        return out

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_opac, _g_extents, _g_visible):
        means, quats, scales, opacities, cam, K = ctx.saved_tensors
        dt = means.dtype
        n = means.shape[0]

        def grad_or_zeros(g, shape):
            return torch.zeros(shape, dtype=dt) if g is None else g.to(dt).contiguous()

        opt = ctx.options
        need_cam, need_K = ctx.needs_input_grad[4], ctx.needs_input_grad[5]
        g_m, g_q, g_s, g_o, g_cam_rows, g_K_rows = _cpu_kernel.project_backward(
            means, quats, scales, opacities, cam, K, opt["width"], opt["height"],
            grad_or_zeros(g_means2d, (n, 2)), grad_or_zeros(g_conics, (n, 3)), grad_or_zeros(g_depths, (n,)),
            grad_or_zeros(g_opac, (n,)), near_plane=opt["near_plane"], far_plane=opt["far_plane"],
            eps2d=opt["eps2d"], antialiased=opt["antialiased"], need_camera=need_cam, need_K=need_K,
            num_threads=opt["num_threads"])
        g_cam = g_K = None
        if need_cam:
            g_cam = torch.zeros(ctx.cam_rows, 4, dtype=dt)
            g_cam[:3] = g_cam_rows.sum(0).reshape(3, 4)
            g_cam = g_cam.to(ctx.in_dtypes[4])
        if need_K:
            fx, fy, cx, cy = g_K_rows.sum(0)
            g_K = torch.zeros(3, 3, dtype=dt)
            g_K[0, 0], g_K[1, 1], g_K[0, 2], g_K[1, 2] = fx, fy, cx, cy
            g_K = g_K.to(ctx.in_dtypes[5])
        grads = [g.to(d) for g, d in zip((g_m, g_q, g_s, g_o), ctx.in_dtypes[:4], strict=True)]
        return (*grads, g_cam, g_K, None)
