"""Render Gaussians into one pinhole view: project -> tile-bin -> sort -> composite.

The functional API of the package (gsplat's `rasterization` for one camera).
Conventions: docs/conventions.md (OpenCV camera axes, `cam_from_world`, pixel
(row, col) evaluated at (col + 0.5, row + 0.5), wxyz quaternions).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mvgeo.common.errors import ShapeError, check_shape
from splat.composite import Backend, composite_tiles
from splat.projection import ProjectedGaussians, project_gaussians
from splat.sh import eval_sh, eval_sh_fast
from splat.tiles import bin_gaussians


@dataclass
class RasterConfig:
    """Options of the rasterizer (defaults are 3DGS / gsplat's).

    Attributes:
        near_plane: Gaussians with camera z below this are culled.
        far_plane: ... and above this.
        eps2d: screen-space low-pass added to the 2D covariance, px^2 (0.3 in 3DGS).
        antialiased: Mip-Splatting opacity compensation for the low-pass.
        tile_size: tile edge in pixels.
        backend: projection, tile binning, SH colour and compositor: "auto" (the C++ kernels on CPU
            when they build, else torch with one warning per process), "torch" (the reference) or "cpp".
        num_threads: threads of the C++ kernels; None: `torch.get_num_threads()` at call time.
    """

    near_plane: float = 0.01
    far_plane: float = 1e10
    eps2d: float = 0.3
    antialiased: bool = False
    tile_size: int = 16
    backend: Backend = "auto"
    num_threads: int | None = None


@dataclass
class RenderOutput:
    """One rendered view.

    Attributes:
        rgb: [3, H, W] colour, background blended in: `sum w_i c_i + T * background`.
        alpha: [1, H, W] accumulated opacity `1 - T`.
        depth: [1, H, W] expected z-depth `sum w_i z_i / alpha` (0 where alpha < 1e-10).
        projected: the screen-space Gaussians (e.g. `means2d` for densification statistics).
        num_intersections: tile-Gaussian pairs processed.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    projected: ProjectedGaussians
    num_intersections: int


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    cam_from_world: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    colors_rest: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    config: RasterConfig | None = None,
) -> RenderOutput:
    """Render one view; differentiable w.r.t. every tensor argument.

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) wxyz (normalised internally).
        scales: (N, 3) activated scales (standard deviations, > 0).
        opacities: (N,) activated opacities in [0, 1].
        colors: (N, 3) RGB when `sh_degree` is None, else (N, K, 3) SH
            coefficients with `K >= (sh_degree + 1) ** 2`; SH colours are
            `max(eval_sh + 0.5, 0)` as in 3DGS / gsplat.
        cam_from_world: (3, 4) or (4, 4) world-to-camera.
        K: (3, 3) pinhole intrinsics (our pixel convention).
        width, height: image size in pixels (>= 1).
        sh_degree: active SH degree 0..3, or None for plain colours.
        colors_rest: with `sh_degree`, the SH bands above the DC one, (N, K - 1, 3), when the caller keeps
            them apart from it (as `GaussianModel` does); `colors` is then the DC band (N, 1, 3). The same as
            passing `torch.cat([colors, colors_rest], 1)`, without copying every coefficient in each render.
        background: (3,) colour behind the Gaussians (default black).
        config: `RasterConfig` (defaults if None).

    Returns:
        `RenderOutput` with tensors on the inputs' device and dtype.
    """
    cfg = config or RasterConfig()
    if width < 1 or height < 1:
        raise ShapeError(f"image size must be at least 1x1, got {width}x{height}")
    n = means.shape[0]
    if sh_degree is None:
        if colors_rest is not None:
            raise ShapeError("colors_rest is SH coefficients; it needs sh_degree")
        check_shape(colors, [n, 3], "colors")
    elif colors_rest is None:
        check_shape(colors, [n, "K", 3], "colors (SH coefficients)")
    else:
        check_shape(colors, [n, 1, 3], "colors (the DC band, with colors_rest)")
        check_shape(colors_rest, [n, "K-1", 3], "colors_rest (SH bands above the DC one)")
    proj = project_gaussians(
        means, quats, scales, opacities, cam_from_world, K, width, height,
        near_plane=cfg.near_plane, far_plane=cfg.far_plane, eps2d=cfg.eps2d, antialiased=cfg.antialiased,
        backend=cfg.backend, num_threads=cfg.num_threads,
    )
    if sh_degree is not None:
        R = cam_from_world[:3, :3]
        cam_centre_world = -(R.T @ cam_from_world[:3, 3])
        # The C++ SH kernel goes with the C++ compositor; backend="torch" stays all-torch (the reference).
        dirs = means - cam_centre_world
        if cfg.backend == "torch":
            sh = eval_sh(sh_degree, colors if colors_rest is None else torch.cat([colors, colors_rest], 1), dirs)
        else:
            sh = eval_sh_fast(sh_degree, colors, dirs, sh_rest=colors_rest, num_threads=cfg.num_threads)
        rgb_g = torch.clamp_min(sh + 0.5, 0.0)
    else:
        rgb_g = colors
    features = torch.cat([rgb_g, proj.depths[:, None]], dim=-1)
    bins = bin_gaussians(proj.means2d, proj.extents_px, proj.depths, proj.visible, width, height,
                         tile_size=cfg.tile_size, backend=cfg.backend)
    accum, trans = composite_tiles(proj.means2d, proj.conics, features, proj.opacities, bins, width, height,
                                   backend=cfg.backend, num_threads=cfg.num_threads)
    alpha = 1.0 - trans
    if background is None:
        rgb = accum[..., :3]
    else:
        check_shape(background, [3], "background")
        rgb = accum[..., :3] + trans[..., None] * background.to(accum.dtype)
    depth = accum[..., 3] / torch.clamp(alpha, min=1e-10)
    return RenderOutput(
        rgb=rgb.permute(2, 0, 1),
        alpha=alpha[None],
        depth=depth[None],
        projected=proj,
        num_intersections=int(bins.gaussian_ids.numel()),
    )
