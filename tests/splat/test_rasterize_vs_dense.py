"""The tile rasterizer (C++ and torch compositors) against the dense float64 reference."""

from __future__ import annotations

import pytest
import torch

from mvgeo.transforms_torch import se3_exp
from splat.rasterize import RasterConfig, rasterize
from tests.splat.backends import BACKENDS
from tests.splat.dense_reference import render_dense
from tests.splat.scenes import random_camera, random_scene


def _render_both(params, delta, focal_scale, cam, K, width, height, backend, *, background, sh_degree,
                 antialiased=False):
    cam_new = se3_exp(delta) @ cam
    K_new = K.clone()
    K_new = torch.diag(torch.stack([focal_scale, focal_scale, torch.ones_like(focal_scale)])) @ K_new
    args = (params["means"], params["quats"], torch.exp(params["log_scales"]),
            torch.sigmoid(params["opacity_logits"]), params["sh"], cam_new, K_new, width, height)
    fast = rasterize(*args, sh_degree=sh_degree, background=background,
                     config=RasterConfig(backend=backend, antialiased=antialiased))
    ref = render_dense(*args, sh_degree=sh_degree, background=background, antialiased=antialiased)
    return (fast.rgb, fast.alpha, fast.depth), ref


def _leaves(n, seed, dtype=torch.float64):
    params = random_scene(n, seed=seed, dtype=dtype)
    for v in params.values():
        v.requires_grad_(True)
    delta = torch.zeros(6, dtype=dtype, requires_grad=True)
    focal_scale = torch.ones((), dtype=dtype, requires_grad=True)
    return params, delta, focal_scale


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("antialiased", [False, True])
def test_images_and_gradients_match_dense(backend, antialiased):
    width, height = 37, 29  # non-square, not a multiple of the tile size
    cam, K = random_camera(width, height, seed=3)
    background = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    weights = None
    grads = {}
    outs = {}
    for which in ("fast", "dense"):
        params, delta, focal_scale = _leaves(60, seed=11)
        fast, ref = _render_both(params, delta, focal_scale, cam, K, width, height, backend,
                                 background=background, sh_degree=3, antialiased=antialiased)
        out = fast if which == "fast" else ref
        outs[which] = [o.detach() for o in out]
        if weights is None:
            g = torch.Generator().manual_seed(5)
            weights = [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in out]
        loss = sum((o * w).sum() for o, w in zip(out, weights, strict=True))
        loss.backward()
        grads[which] = {**{k: v.grad.clone() for k, v in params.items()}, "pose": delta.grad.clone(),
                        "focal": focal_scale.grad.clone().reshape(1)}
    # Images: same float64 arithmetic up to summation order -> 1e-5 is loose (observed ~1e-12).
    for name, a, b in zip(("rgb", "alpha", "depth"), outs["fast"], outs["dense"], strict=True):
        assert torch.isfinite(a).all()
        scale = 1.0 if name != "depth" else float(b.abs().max())  # depth is ~3 units: compare relatively
        assert (a - b).abs().max().item() <= 1e-5 * scale, name
    assert outs["dense"][1].max() > 0.5  # the scene really covers the image
    # Gradients: issue's acceptance bound, rel. L2 < 1e-4 and cosine > 0.9999 per parameter.
    for key, gd in grads["dense"].items():
        gf = grads["fast"][key]
        assert gd.norm() > 0, key
        rel = ((gf - gd).norm() / gd.norm()).item()
        cos = torch.nn.functional.cosine_similarity(gf.reshape(1, -1), gd.reshape(1, -1)).item()
        assert rel < 1e-4 and cos > 0.9999, (key, rel, cos)


@pytest.mark.parametrize("backend", BACKENDS)
def test_float32_matches_dense(backend):
    """float32 (the training dtype) against float64: rounding only, 1e-4 absolute on [0, 1] colours."""
    width, height = 33, 21
    cam, K = random_camera(width, height, seed=4)
    p64 = random_scene(40, seed=12)
    ref = render_dense(p64["means"], p64["quats"], torch.exp(p64["log_scales"]), torch.sigmoid(p64["opacity_logits"]),
                       p64["sh"], cam, K,
                       width, height, sh_degree=3)
    p32 = {k: v.float() for k, v in p64.items()}
    fast = rasterize(p32["means"], p32["quats"], torch.exp(p32["log_scales"]), torch.sigmoid(p32["opacity_logits"]),
                     p32["sh"], cam.float(), K.float(), width, height, sh_degree=3,
                     config=RasterConfig(backend=backend))
    assert fast.rgb.dtype == torch.float32
    assert (fast.rgb.double() - ref[0]).abs().max() < 1e-4
    assert (fast.alpha.double() - ref[1]).abs().max() < 1e-4


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_small(backend):
    """float64 finite differences vs the analytic/autograd backward on a tiny scene."""
    width, height = 11, 9
    cam, K = random_camera(width, height, seed=6)
    params = random_scene(5, seed=13, sh_degree=1, scale_range=(0.15, 0.3))
    names = ["means", "quats", "log_scales", "opacity_logits", "sh"]
    inputs = [params[k].clone().requires_grad_(True) for k in names] + [
        torch.zeros(6, dtype=torch.float64, requires_grad=True)]

    def fn(means, quats, log_scales, logits, sh, delta):
        out = rasterize(means, quats, torch.exp(log_scales), torch.sigmoid(logits), sh, se3_exp(delta) @ cam, K,
                        width, height, sh_degree=1, background=torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64),
                        config=RasterConfig(backend=backend))
        return out.rgb, out.alpha, out.depth

    # eps 1e-6 / atol 1e-5: central differences of a smooth function in float64; the
    # alpha thresholds are discontinuities, none of which lies within eps on this scene.
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sh_bands_apart_render_as_joined(backend):
    """`colors_rest` (a model's DC band and other bands passed apart, as `GaussianModel.render` passes them) gives
    the image and every gradient of the joined coefficients, bit for bit: the same numbers in the same order."""
    width, height = 37, 29
    cam, K = random_camera(width, height, seed=5)
    results = []
    for apart in (False, True):
        params, delta, _ = _leaves(60, seed=5)
        sh = params["sh"]
        sh0 = sh[:, :1].detach().clone().requires_grad_(True)
        rest = sh[:, 1:].detach().clone().requires_grad_(True)
        colors = (sh0, rest) if apart else (torch.cat([sh0, rest], 1),)
        out = rasterize(params["means"], params["quats"], torch.exp(params["log_scales"]),
                        torch.sigmoid(params["opacity_logits"]), colors[0], se3_exp(delta) @ cam, K, width, height,
                        sh_degree=3, colors_rest=colors[1] if apart else None, background=torch.full((3,), 0.2,
                                                                                                   dtype=sh.dtype),
                        config=RasterConfig(backend=backend))
        (out.rgb * torch.linspace(-1, 1, out.rgb.numel(), dtype=sh.dtype).reshape(out.rgb.shape)).sum().backward()
        results.append([out.rgb.detach(), sh0.grad, rest.grad, delta.grad, params["means"].grad])
    for a, b in zip(*results, strict=True):
        assert torch.equal(a, b)
    assert results[0][2].abs().max() > 0  # the higher bands do get a gradient


def test_colors_rest_needs_sh_coefficients():
    from mvgeo.common.errors import ShapeError

    cam, K = random_camera(8, 8, seed=0)
    params = random_scene(4, seed=0)
    with pytest.raises(ShapeError, match="colors_rest"):
        rasterize(params["means"], params["quats"], torch.exp(params["log_scales"]),
                  torch.sigmoid(params["opacity_logits"]), params["sh"][:, 0], cam, K, 8, 8,
                  colors_rest=params["sh"][:, 1:])
    with pytest.raises(ShapeError, match="DC band"):
        rasterize(params["means"], params["quats"], torch.exp(params["log_scales"]),
                  torch.sigmoid(params["opacity_logits"]), params["sh"], cam, K, 8, 8, sh_degree=3,
                  colors_rest=params["sh"][:, 1:])
