"""The fused C++ L1 + SSIM loss (`splat/csrc/ssim.cpp`) against the torch reference path of
`splat.losses.photometric_loss` (mvgeo.image_metrics.ssim + autograd): values, gradients, a
finite-difference gradient check, thread-count independence and the fallbacks."""

from __future__ import annotations

import pytest
import torch

from splat import _cpu_kernel
from splat.losses import photometric_loss

pytestmark = pytest.mark.skipif(not _cpu_kernel.available(), reason="C++ splat kernels unavailable")

# Shapes: both axes at the window size (no interior on either), one axis below twice the radius
# beyond it, odd sizes, a wide image, a single channel.
SHAPES = [(3, 11, 11), (3, 12, 11), (3, 20, 33), (3, 64, 48), (1, 13, 70), (3, 37, 12)]


def _loss_and_grad(x: torch.Tensor, y: torch.Tensor, backend: str, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    x = x.detach().clone().requires_grad_(True)
    loss = photometric_loss(x, y, backend=backend, **kw)
    (g,) = torch.autograd.grad(loss, x)
    return loss.detach(), g


def _pair(shape, dtype, seed=0):
    gen = torch.Generator().manual_seed(seed)
    # A smooth image plus noise, and a target close to it: SSIM well inside (0, 1), as in training.
    x = torch.rand(shape, generator=gen, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    return x.to(dtype), y.to(dtype)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("weight", [0.2, 1.0])
def test_cpp_loss_matches_torch_reference_float64(shape, weight):
    x, y = _pair(shape, torch.float64)
    ref, g_ref = _loss_and_grad(x, y, "torch", ssim_weight=weight)
    out, g_out = _loss_and_grad(x, y, "cpp", ssim_weight=weight)
    # Same formulas, other summation order: float64 rounding only (~1e-16 per term, a few hundred terms).
    assert float(out) == pytest.approx(float(ref), abs=1e-12)
    assert torch.allclose(g_out, g_ref, rtol=0, atol=1e-12 * float(g_ref.abs().max()) + 1e-15)


@pytest.mark.parametrize("shape", [(3, 20, 33), (3, 96, 128)])
def test_cpp_loss_matches_torch_reference_float32(shape):
    x, y = _pair(shape, torch.float32, seed=1)
    ref, g_ref = _loss_and_grad(x, y, "torch")
    out, g_out = _loss_and_grad(x, y, "cpp")
    # float32: each moment is a 121-term sum (relative error ~1e-6), and the variance
    # E[x^2] - mx^2 cancels about one digit more; both paths carry that error independently.
    assert float(out) == pytest.approx(float(ref), rel=1e-5)
    assert torch.allclose(g_out, g_ref, rtol=0, atol=1e-4 * float(g_ref.abs().max()))


def test_cpp_loss_gradcheck():
    x, y = _pair((2, 12, 14), torch.float64, seed=2)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: photometric_loss(t, y, backend="cpp"), (x,), eps=1e-6, atol=1e-8)


def test_cpp_loss_does_not_depend_on_threads():
    x, y = _pair((3, 50, 61), torch.float32, seed=3)
    a, ga = _loss_and_grad(x, y, "cpp", num_threads=1)
    b, gb = _loss_and_grad(x, y, "cpp", num_threads=3)
    assert torch.equal(a, b) and torch.equal(ga, gb)


def test_identical_images_give_zero_loss_and_gradient():
    x, _ = _pair((3, 16, 16), torch.float64, seed=4)
    loss, g = _loss_and_grad(x, x.clone(), "cpp")
    assert abs(float(loss)) < 1e-12
    # SSIM is at its maximum and L1's subgradient at 0 is 0 (as torch's abs).
    assert float(g.abs().max()) < 1e-12


def test_auto_uses_torch_when_the_target_needs_a_gradient():
    x, y = _pair((3, 16, 16), torch.float64, seed=5)
    y.requires_grad_(True)
    loss = photometric_loss(x, y)
    (gy,) = torch.autograd.grad(loss, y)
    assert gy.abs().sum() > 0
    with pytest.raises(ValueError, match="target without gradient"):
        photometric_loss(x, y, backend="cpp")


def test_mixed_dtypes_take_the_torch_path():
    # A float32 render against a float64 target: "auto" computes as the torch reference does (no silent
    # cast of the target to float32); "cpp" refuses.
    x, y = _pair((3, 16, 16), torch.float64, seed=7)
    x32 = x.float()
    assert float(photometric_loss(x32, y)) == float(photometric_loss(x32, y, backend="torch"))
    with pytest.raises(ValueError, match="dtype"):
        photometric_loss(x32, y, backend="cpp")


def test_second_derivatives_are_refused_not_zero():
    x, y = _pair((3, 16, 16), torch.float64, seed=8)
    x.requires_grad_(True)
    (g,) = torch.autograd.grad(photometric_loss(x, y, backend="cpp"), x, create_graph=True)
    with pytest.raises(RuntimeError):
        torch.autograd.grad(g.sum(), x)


def test_small_images_fall_back_to_l1():
    x, y = _pair((3, 8, 20), torch.float64, seed=6)
    out = photometric_loss(x, y, backend="cpp")
    assert float(out) == pytest.approx(float((x - y).abs().mean()), abs=1e-15)


def test_unknown_backend_is_refused():
    x, y = _pair((3, 16, 16), torch.float64)
    with pytest.raises(ValueError, match="backend"):
        photometric_loss(x, y, backend="fast")  # type: ignore[arg-type]
