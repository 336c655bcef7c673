"""Behaviour near singularities: outputs and gradients stay finite (both compositors)."""

from __future__ import annotations

import pytest
import torch

from splat.rasterize import RasterConfig, rasterize
from tests.splat.backends import BACKENDS
from tests.splat.dense_reference import render_dense

DT = torch.float64


def _cam():
    return torch.eye(4, dtype=DT)[:3]


def _K(w, h, f=30.0):
    return torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=DT)


def _render_and_grad(means, quats, scales, opac, colors, w, h, backend, K=None):
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    delta = torch.zeros(3, dtype=DT, requires_grad=True)
    cam = _cam().clone()
    cam = torch.cat([cam[:, :3], (cam[:, 3] + delta)[:, None]], 1)
    out = rasterize(*leaves, cam, _K(w, h) if K is None else K, w, h,
                    background=torch.tensor([0.3, 0.3, 0.3], dtype=DT), config=RasterConfig(backend=backend))
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    for t in (out.rgb, out.alpha, out.depth):
        assert torch.isfinite(t).all()
    for leaf in [*leaves, delta]:
        assert leaf.grad is not None and torch.isfinite(leaf.grad).all()
    return out, leaves


def _one(mean, scale=(0.1, 0.1, 0.1), opacity=0.8, quat=(1.0, 0.0, 0.0, 0.0)):
    return (torch.tensor([mean], dtype=DT), torch.tensor([quat], dtype=DT), torch.tensor([scale], dtype=DT),
            torch.tensor([opacity], dtype=DT), torch.tensor([[0.9, 0.2, 0.1]], dtype=DT))


@pytest.mark.parametrize("backend", BACKENDS)
def test_behind_camera_and_straddling_near_plane(backend):
    g = _one([0.0, 0.0, -1.0])
    out, leaves = _render_and_grad(*g, 16, 12, backend)
    assert out.alpha.max() == 0  # behind: culled
    assert (leaves[0].grad == 0).all()
    # Mean just in front of the near plane (0.01) with a scale reaching behind the camera: kept, finite.
    out, _ = _render_and_grad(*_one([0.0, 0.0, 0.011], scale=(0.5, 0.5, 0.5)), 16, 12, backend)
    assert out.alpha.max() > 0.5  # kept: it covers the view at nearly its opacity (0.8)
    # Mean just behind it: culled, no contribution.
    out, _ = _render_and_grad(*_one([0.0, 0.0, 0.009], scale=(0.5, 0.5, 0.5)), 16, 12, backend)
    assert out.alpha.max() == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_on_and_beyond_border(backend):
    means = torch.tensor([[-0.27, 0.0, 1.0], [0.0, 0.2, 1.0], [50.0, 0.0, 1.0], [0.0, -80.0, 2.0]], dtype=DT)
    n = len(means)
    quats = torch.tensor([[1.0, 0, 0, 0]] * n, dtype=DT)
    scales = torch.full((n, 3), 0.05, dtype=DT)
    out, leaves = _render_and_grad(means, quats, scales, torch.full((n,), 0.9, dtype=DT),
                                   torch.rand(n, 3, dtype=DT, generator=torch.Generator().manual_seed(0)),
                                   16, 12, backend)
    assert out.alpha[0, :, 0].max() > 0.1  # the one centred on the left border shows
    assert (leaves[0].grad[2:] == 0).all()  # far outside: culled


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("scale", [(1e-4, 1e-4, 1.0), (1.0, 1.0, 1e-4), (1e-6, 1e2, 1e-6)])
def test_thin_and_huge_covariances(backend, scale):
    """Scale ratios up to 1e8 (condition number 1e16 of the covariance), rotated: finite, and the image of the
    dense per-pixel reference. Tolerance: inverting a covariance of condition number 1e16 in float64 loses
    most of its digits (measured 8e-11 on the needle), far below any visible difference."""
    q = torch.tensor([0.9, 0.3, -0.2, 0.1], dtype=DT)
    g = _one([0.05, -0.03, 1.5], scale=scale, quat=tuple(q.tolist()))
    out, leaves = _render_and_grad(*g, 20, 15, backend)
    rgb, alpha, _ = render_dense(*g, _cam(), _K(20, 15), 20, 15, background=torch.tensor([0.3, 0.3, 0.3], dtype=DT))
    assert out.alpha.max() > 0.5  # the Gaussian shows (opacity 0.8)
    torch.testing.assert_close(out.alpha, alpha, atol=1e-8, rtol=0)
    torch.testing.assert_close(out.rgb, rgb, atol=1e-8, rtol=0)
    assert leaves[0].grad.abs().max() > 0  # and its mean receives a gradient


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("opacity", [0.0, 1e-9, 1.0 - 1e-12, 1.0])
def test_extreme_opacities(backend, opacity):
    # Mean projected exactly onto pixel (8, 6)'s centre (u = 30 x / z + 8 = 8.5), so sigma = 0 there.
    out, _ = _render_and_grad(*_one([1 / 60, 1 / 60, 1.0], opacity=opacity), 16, 12, backend)
    if opacity < 1 / 255:
        assert out.alpha.max() == 0
    else:
        assert abs(out.alpha.max().item() - 0.99) < 1e-9  # alpha is clamped at 0.99


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene(backend):
    z = torch.zeros(0, 3, dtype=DT)
    out, _ = _render_and_grad(z, torch.zeros(0, 4, dtype=DT), z, torch.zeros(0, dtype=DT), z, 16, 12, backend)
    assert (out.rgb == 0.3).all() and (out.alpha == 0).all() and (out.depth == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_gaussian_covering_everything_and_many_stacked(backend):
    out, _ = _render_and_grad(*_one([0.0, 0.0, 1.0], scale=(10.0, 10.0, 10.0), opacity=0.5), 24, 17, backend)
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 0.5), atol=1e-3)
    # 40 opaque layers: transmittance termination kicks in, the result stays finite and ~opaque.
    n = 40
    means = torch.stack([torch.zeros(n), torch.zeros(n), torch.linspace(1, 2, n)], 1).to(DT)
    out, _ = _render_and_grad(means, torch.tensor([[1.0, 0, 0, 0]] * n, dtype=DT), torch.full((n, 3), 5.0, dtype=DT),
                              torch.full((n,), 0.9, dtype=DT), torch.rand(n, 3, dtype=DT), 8, 8, backend)
    assert out.alpha.min() > 1 - 1e-3


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("wh", [(1, 1), (1, 7), (33, 2)])
def test_tiny_and_non_square_images(backend, wh):
    w, h = wh
    out, _ = _render_and_grad(*_one([0.0, 0.0, 1.0], scale=(0.2, 0.2, 0.2)), w, h, backend)
    assert out.rgb.shape == (3, h, w) and out.alpha.shape == (1, h, w)
    assert out.alpha.max() > 0
