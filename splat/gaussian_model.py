"""`GaussianModel`: the learnable parameters of a 3D Gaussian scene.

Parameters are stored pre-activation, as in 3DGS and its PLY format:
`means (N, 3)`, `quats (N, 4)` wxyz (unnormalised), `log_scales (N, 3)`,
`opacity_logits (N,)`, `sh0 (N, 1, 3)` (DC), `shN (N, K - 1, 3)` with
`K = (sh_degree_max + 1) ** 2`. Activations: `normalize`, `exp`, `sigmoid`.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from mvgeo.common.errors import InputError, check_shape
from splat.rasterize import RasterConfig, RenderOutput, rasterize
from splat.sh import num_sh_bases, rgb_to_sh_dc

#: Parameter names, in the order used by optimizers and checkpoints.
PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")


class GaussianModel(torch.nn.Module):
    """Learnable Gaussians (a thin holder; rendering is `splat.rasterize`).

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) wxyz.
        log_scales: (N, 3) natural log of the standard deviations.
        opacity_logits: (N,) logit of opacity.
        sh0: (N, 1, 3) SH DC coefficients.
        shN: (N, K - 1, 3) higher-order SH coefficients (K - 1 may be 0).
    """

    def __init__(self, means, quats, log_scales, opacity_logits, sh0, shN):
        super().__init__()
        n = means.shape[0]
        check_shape(means, [n, 3], "means")
        check_shape(quats, [n, 4], "quats")
        check_shape(log_scales, [n, 3], "log_scales")
        check_shape(opacity_logits, [n], "opacity_logits")
        check_shape(sh0, [n, 1, 3], "sh0")
        check_shape(shN, [n, "K-1", 3], "shN")
        k = shN.shape[1] + 1
        if k not in (1, 4, 9, 16):
            raise InputError(f"SH coefficient count {k} is not (degree + 1)^2 for degree 0..3")
        for name, value in zip(PARAM_NAMES, (means, quats, log_scales, opacity_logits, sh0, shN), strict=True):
            self.register_parameter(name, torch.nn.Parameter(value.detach().clone()))

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree_max(self) -> int:
        return int(round((self.shN.shape[1] + 1) ** 0.5)) - 1

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def sh(self) -> torch.Tensor:
        """(N, K, 3) all SH coefficients."""
        return torch.cat([self.sh0, self.shN], dim=1)

    def params_dict(self) -> dict[str, torch.nn.Parameter]:
        return {name: getattr(self, name) for name in PARAM_NAMES}

    @classmethod
    def from_points(cls, points_xyz: np.ndarray, points_rgb: np.ndarray, *, sh_degree: int = 3,
                    init_opacity: float = 0.1, scale_factor: float = 1.0, dtype=torch.float32,
                    device: str | torch.device = "cpu") -> GaussianModel:
        """3DGS / InstantSplat initialisation from a coloured point cloud.

        Colour -> SH DC, isotropic scale = RMS distance to the 3 nearest
        neighbours (times `scale_factor`), identity rotation, opacity 0.1.

        Args:
            points_xyz: (P, 3) world points, P >= 2.
            points_rgb: (P, 3) colours, uint8 or float in [0, 1].
            sh_degree: maximum SH degree 0..3 (higher coefficients start at 0).
            init_opacity: initial opacity in (0, 1).
            scale_factor: multiplies the nearest-neighbour scale.

        Raises:
            InputError: fewer than 2 points, mismatched lengths or non-finite points.
        """
        xyz = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
        rgb = np.asarray(points_rgb)
        if rgb.dtype == np.uint8:
            rgb = rgb.astype(np.float64) / 255.0
        rgb = np.asarray(rgb, dtype=np.float64).reshape(-1, 3)
        if len(xyz) < 2:
            raise InputError(f"need at least 2 initial points, got {len(xyz)}",
                             fix="initialise from a sparse model with a point cloud (points3D) or pass --init")
        if len(xyz) != len(rgb):
            raise InputError(f"{len(xyz)} points but {len(rgb)} colours")
        if not np.isfinite(xyz).all():
            raise InputError("initial points contain NaN or inf")
        if not 0.0 < init_opacity < 1.0:
            raise InputError(f"init_opacity must be in (0, 1), got {init_opacity}")
        k = min(4, len(xyz))
        dist, _ = cKDTree(xyz).query(xyz, k=k)
        nn_d2 = np.mean(dist[:, 1:] ** 2, axis=1)
        positive = nn_d2[nn_d2 > 0]
        floor = float(np.median(positive)) * 1e-2 if positive.size else 1e-6
        scale = np.sqrt(np.maximum(nn_d2, max(floor, 1e-14))) * scale_factor
        n = len(xyz)
        kk = num_sh_bases(sh_degree)

        def t(a):
            return torch.as_tensor(np.asarray(a), dtype=dtype, device=device)

        quats = np.zeros((n, 4))
        quats[:, 0] = 1.0
        logit = np.log(init_opacity / (1.0 - init_opacity))
        return cls(
            means=t(xyz),
            quats=t(quats),
            log_scales=t(np.repeat(np.log(scale)[:, None], 3, axis=1)),
            opacity_logits=t(np.full(n, logit)),
            sh0=rgb_to_sh_dc(t(np.clip(rgb, 0.0, 1.0)))[:, None, :],
            shN=torch.zeros(n, kk - 1, 3, dtype=dtype, device=device),
        )

    def render(self, cam_from_world: torch.Tensor, K: torch.Tensor, width: int, height: int, *,
               sh_degree: int | None = None, background: torch.Tensor | None = None,
               config: RasterConfig | None = None) -> RenderOutput:
        """Render one view with the active SH degree (default: the maximum)."""
        degree = self.sh_degree_max if sh_degree is None else sh_degree
        return rasterize(self.means, self.quats, self.scales, self.opacities, self.sh0,
                         cam_from_world.to(self.means), K.to(self.means), width, height,
                         sh_degree=degree, colors_rest=self.shN, background=background, config=config)
