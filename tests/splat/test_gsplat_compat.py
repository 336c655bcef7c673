"""Same inputs, same image as gsplat (needs CUDA and gsplat; skipped otherwise)."""

from __future__ import annotations

import pytest
import torch

from splat.rasterize import RasterConfig, rasterize
from tests.splat.scenes import activated, random_camera, random_scene

gsplat = pytest.importorskip("gsplat")
pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


def test_matches_gsplat_rasterization():
    W, H = 96, 64
    cam, K = random_camera(W, H, seed=51, dtype=torch.float32)
    means, quats, scales, opac, sh = (t.float().cuda() for t in activated(random_scene(500, seed=52)))
    cam, K = cam.cuda(), K.cuda()
    ref, ref_alpha, _ = gsplat.rasterization(means, quats, scales, opac, sh, cam[None], K[None], W, H,
                                             sh_degree=3, packed=False)
    ours = rasterize(means, quats, scales, opac, sh, cam, K, W, H, sh_degree=3, config=RasterConfig(backend="torch"))
    # float32 on both sides, different summation order: 1e-4 on [0, 1] colours.
    assert (ours.rgb.permute(1, 2, 0) - ref[0]).abs().max() < 1e-4
    assert (ours.alpha[0] - ref_alpha[0, ..., 0]).abs().max() < 1e-4
