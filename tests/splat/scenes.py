"""Small random Gaussian scenes and cameras shared by the splat tests."""

from __future__ import annotations

import math

import torch

from mvgeo.transforms_torch import se3_exp


def look_at_cam_from_world(eye, target, dtype=torch.float64) -> torch.Tensor:
    """(4, 4) OpenCV-axes cam_from_world looking from `eye` to `target` (y down)."""
    eye = torch.as_tensor(eye, dtype=dtype)
    target = torch.as_tensor(target, dtype=dtype)
    z = target - eye
    z = z / z.norm()
    up = torch.tensor([0.0, -1.0, 0.0], dtype=dtype)
    x = torch.linalg.cross(up, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    out = torch.eye(4, dtype=dtype)
    out[:3, :3] = R
    out[:3, 3] = -R @ eye
    return out


def random_scene(n: int, *, seed: int, dtype=torch.float64, sh_degree: int = 3, spread: float = 0.6,
                 scale_range=(0.03, 0.15)):
    """Gaussians around the origin, seen by a camera 3 units away (pre-activation parameters)."""
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2

    def rnd(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    params = {
        "means": (rnd(n, 3) - 0.5) * 2 * spread,
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "log_scales": torch.log(scale_range[0] + rnd(n, 3) * (scale_range[1] - scale_range[0])),
        "opacity_logits": torch.logit(0.15 + 0.75 * rnd(n)),
        "sh": torch.cat([(rnd(n, 1, 3) - 0.5) * 2.0, (rnd(n, k - 1, 3) - 0.5) * 0.4], 1),
    }
    return params


def random_camera(width: int, height: int, *, seed: int, dtype=torch.float64):
    """A slightly rotated camera 3 units from the origin; K with fx != fy and an off-centre principal point."""
    g = torch.Generator().manual_seed(seed + 1000)
    cam = look_at_cam_from_world([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], dtype=dtype)
    jitter = se3_exp((torch.rand(6, generator=g, dtype=dtype) - 0.5) * 0.1)
    cam = jitter @ cam
    f = 1.2 * max(width, height)
    K = torch.tensor([[f, 0.0, 0.52 * width], [0.0, 0.95 * f, 0.47 * height], [0.0, 0.0, 1.0]], dtype=dtype)
    return cam, K


def activated(params, sh_degree=3):
    """Parameters as the renderer takes them."""
    return (params["means"], params["quats"], torch.exp(params["log_scales"]),
            torch.sigmoid(params["opacity_logits"]), params["sh"])


def fov_deg(width: int, f: float) -> float:
    return math.degrees(2 * math.atan(0.5 * width / f))
