"""Tile binning is an exact superset of contributing pairs; projection agrees with OpenCV."""

from __future__ import annotations

import numpy as np
import torch

from mvgeo.common.deps import cv2
from splat.projection import ALPHA_MIN, project_gaussians
from splat.tiles import bin_gaussians
from tests.splat.scenes import activated, random_camera, random_scene


def test_bins_contain_every_contributing_pair():
    W, H = 45, 38
    cam, K = random_camera(W, H, seed=21)
    means, quats, scales, opac, _ = activated(random_scene(80, seed=22))
    p = project_gaussians(means, quats, scales, opac, cam, K, W, H)
    bins = bin_gaussians(p.means2d, p.extents_px, p.depths, p.visible, W, H, tile_size=8)
    listed = set()
    for t in range(bins.tiles_x * bins.tiles_y):
        ids = bins.gaussian_ids[bins.tile_offsets[t]:bins.tile_offsets[t + 1]]
        d = p.depths[ids]
        assert (d[1:] >= d[:-1]).all()  # front to back within a tile
        listed |= {(t, int(i)) for i in ids}
    # Brute force: every (pixel, Gaussian) with alpha >= 1/255 must be in its tile's list.
    rows, cols = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    px = torch.stack([cols.reshape(-1) + 0.5, rows.reshape(-1) + 0.5], -1).double()
    tile = (rows.reshape(-1) // 8) * bins.tiles_x + cols.reshape(-1) // 8
    for i in torch.nonzero(p.visible).reshape(-1).tolist():
        d = p.means2d[i] - px
        a, b, c = p.conics[i]
        alpha = p.opacities[i] * torch.exp(-(0.5 * (a * d[:, 0] ** 2 + c * d[:, 1] ** 2) + b * d[:, 0] * d[:, 1]))
        for t in set(tile[alpha >= ALPHA_MIN].tolist()):
            assert (t, i) in listed


def test_means2d_match_opencv():
    W, H = 64, 48
    cam, K = random_camera(W, H, seed=31)
    means = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0], [-0.4, 0.2, -0.1]], dtype=torch.float64)
    p = project_gaussians(means, torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64),
                          torch.full((3, 3), 0.1, dtype=torch.float64), torch.full((3,), 0.5, dtype=torch.float64),
                          cam, K, W, H)
    rvec, _ = cv2.Rodrigues(cam[:3, :3].numpy())
    K_cv = K.numpy().copy()
    K_cv[:2, 2] -= 0.5  # OpenCV's top-left pixel centre is (0, 0); ours is (0.5, 0.5)
    uv_cv, _ = cv2.projectPoints(means.numpy(), rvec, cam[:3, 3].numpy(), K_cv, None)
    # float64 both sides: agreement to rounding.
    np.testing.assert_allclose(p.means2d.numpy(), uv_cv[:, 0] + 0.5, atol=1e-9)


def test_projection_gradcheck():
    W, H = 30, 20
    cam, K = random_camera(W, H, seed=41)
    means, quats, scales, opac, _ = activated(random_scene(6, seed=42))
    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, cam, K)]

    def fn(*args):
        p = project_gaussians(*args, W, H, antialiased=True)
        return p.means2d, p.conics, p.depths, p.opacities

    # float64 central differences on smooth functions (no Jacobian clamp is active for these in-view Gaussians).
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_float32_thin_gaussians_keep_their_2d_covariance():
    # A needle's 2D covariance has det = a c - b^2 = |T0 x T1|^2, tiny next to a c: in float32 that difference
    # lost every digit for ~100 px long, sub-pixel thin Gaussians, and with it the antialiased opacity
    # compensation sqrt(det / det_aa) (17 % of these needles off by > 10 %, some culled) and the conics.
    # The float32 path must stay within float32 rounding of the float64 one.
    g = torch.Generator().manual_seed(0)
    n = 2000
    W, H = 200, 150
    K = torch.tensor([[200.0, 0, 100], [0, 200, 75], [0, 0, 1]], dtype=torch.float64)
    means = torch.cat([torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5,
                       torch.full((n, 1), 2.0, dtype=torch.float64)], 1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    long = torch.exp(torch.rand(n, generator=g, dtype=torch.float64) * 4 - 4)  # 2 to 100 px
    thin = torch.exp(torch.rand(n, generator=g, dtype=torch.float64) * 6 - 12)  # 6e-4 to 0.25 px
    scales = torch.stack([long, thin, 1.3 * thin], 1)
    opac = torch.full((n,), 0.9, dtype=torch.float64)
    cam = torch.eye(4, dtype=torch.float64)[:3]
    args64 = (means, quats, scales, opac, cam, K)
    ref = project_gaussians(*args64, W, H, antialiased=True, backend="torch")
    got = project_gaussians(*(t.float() for t in args64), W, H, antialiased=True, backend="torch")
    assert got.conics.dtype == torch.float32 and got.extents_px.dtype == torch.float32
    assert torch.equal(got.visible, ref.visible)
    torch.testing.assert_close(got.opacities.double(), ref.opacities, rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(got.conics.double(), ref.conics, rtol=1e-3, atol=1e-6)
