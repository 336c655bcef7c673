"""Real SH basis: orthonormal on the sphere; DC round trip; the C++ kernel against the torch reference."""

from __future__ import annotations

import math

import pytest
import torch

from splat.sh import eval_sh, eval_sh_fast, rgb_to_sh_dc, sh_basis, sh_dc_to_rgb


def test_basis_orthonormal():
    # Fibonacci sphere quadrature with 20k points integrates degree <= 6 products to ~1e-4.
    n = 20000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = torch.sqrt(1 - z * z)
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    Y = sh_basis(3, dirs)
    gram = (Y.T @ Y) * (4 * math.pi / n)
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=1e-3)


def test_dc_round_trip_and_degree_use():
    rgb = torch.tensor([[0.1, 0.5, 0.9]], dtype=torch.float64)
    assert torch.allclose(sh_dc_to_rgb(rgb_to_sh_dc(rgb)), rgb)
    sh = torch.zeros(1, 16, 3, dtype=torch.float64)
    sh[:, 0] = rgb_to_sh_dc(rgb)
    sh[:, 1:] = 5.0  # higher bands ignored at degree 0
    out = eval_sh(0, sh, torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)) + 0.5
    assert torch.allclose(out, rgb)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpp_sh_matches_torch_values_and_gradients(degree, dtype, cpp_kernel):
    g = torch.Generator().manual_seed(degree)
    n = 200
    sh = torch.randn(n, 16, 3, generator=g, dtype=dtype)  # more bases than used: the rest get zero gradient
    dirs = torch.randn(n, 3, generator=g, dtype=dtype) * torch.rand(n, 1, generator=g, dtype=dtype) * 5
    dirs[0] = 0.0  # zero direction: DC only
    dirs[1] = torch.tensor([1e-14, -2e-14, 0.0], dtype=dtype)  # below normalize's eps
    w = torch.randn(n, 3, generator=g, dtype=dtype)
    results = []
    for fn in (eval_sh_fast, eval_sh):
        leaves = [sh.clone().requires_grad_(True), dirs.clone().requires_grad_(True)]
        out = fn(degree, *leaves)
        (out * w).sum().backward()
        # (degree 0: the torch graph does not reach dirs, grad None = zero)
        results.append([out.detach()] + [t.grad if t.grad is not None else torch.zeros_like(t) for t in leaves])
    # Same formulas, different operation order: float64 ~1e-15, float32 ~1e-6 relative to the magnitudes.
    tol = 1e-11 if dtype == torch.float64 else 2e-5
    for name, a, b in zip(["colour", "d sh", "d dirs"], *results, strict=True):
        scale = b.abs().max().clamp(min=1.0)
        assert torch.allclose(a, b, rtol=0, atol=tol * scale), (name, float((a - b).abs().max()))
    assert (results[0][1][:, (degree + 1) ** 2:] == 0).all()


def test_cpp_sh_is_independent_of_the_thread_count(cpp_kernel):
    # 5000 Gaussians: three of the kernel's 2048-Gaussian work items, the last one partial.
    g = torch.Generator().manual_seed(3)
    sh = torch.randn(5000, 16, 3, generator=g)
    dirs = torch.randn(5000, 3, generator=g)
    w = torch.randn(5000, 3, generator=g)
    results = []
    for threads in (1, 3):
        leaves = [sh.clone().requires_grad_(True), dirs.clone().requires_grad_(True)]
        out = eval_sh_fast(3, *leaves, num_threads=threads)
        (out * w).sum().backward()
        results.append([out.detach(), leaves[0].grad, leaves[1].grad])
    for a, b in zip(*results, strict=True):
        assert torch.equal(a, b)
    assert torch.allclose(results[0][0], eval_sh(3, sh, dirs), atol=2e-5)  # and it is the SH colour


def test_cpp_sh_gradcheck(cpp_kernel):
    g = torch.Generator().manual_seed(0)
    sh = torch.randn(5, 16, 3, generator=g, dtype=torch.float64, requires_grad=True)
    dirs = torch.randn(5, 3, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, d: eval_sh_fast(3, s, d), (sh, dirs), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("k_total", [1, 4, 16])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpp_sh_with_separate_bands_is_the_one_tensor_result(k_total, dtype, cpp_kernel):
    """A model's DC band and other bands passed apart (`sh_rest`) give the values and gradients of the joined
    tensor, bit for bit (the kernel reads the same numbers in the same order), at every degree the bands allow."""
    g = torch.Generator().manual_seed(k_total)
    n = 300
    sh = torch.randn(n, k_total, 3, generator=g, dtype=dtype)
    dirs = torch.randn(n, 3, generator=g, dtype=dtype)
    w = torch.randn(n, 3, generator=g, dtype=dtype)
    for degree in range(int(round(k_total ** 0.5))):
        joined = [sh.clone().requires_grad_(True), dirs.clone().requires_grad_(True)]
        out_j = eval_sh_fast(degree, *joined)
        (out_j * w).sum().backward()
        parts = [sh[:, :1].clone().requires_grad_(True), sh[:, 1:].clone().requires_grad_(True),
                 dirs.clone().requires_grad_(True)]
        out_p = eval_sh_fast(degree, parts[0], parts[2], sh_rest=parts[1])
        (out_p * w).sum().backward()
        assert torch.equal(out_p, out_j)
        assert torch.equal(parts[0].grad, joined[0].grad[:, :1])
        assert torch.equal(parts[1].grad, joined[0].grad[:, 1:])
        assert torch.equal(parts[2].grad, joined[1].grad)
        # and against the torch reference
        assert torch.allclose(out_p, eval_sh(degree, sh, dirs), rtol=0,
                              atol=1e-11 if dtype == torch.float64 else 2e-5)


def test_cpp_sh_separate_bands_strided_inputs_and_frozen_coefficients(cpp_kernel):
    """Bands that are not dense (a transposed view) are copied, not misread; a frozen part gets no gradient and
    the other parts the reference's (the test-time pose fit freezes both; a colour refit may freeze one)."""
    g = torch.Generator().manual_seed(7)
    n = 64
    sh = torch.randn(n, 16, 3, generator=g, dtype=torch.float64)
    dirs = torch.randn(n, 3, generator=g, dtype=torch.float64)
    w = torch.randn(n, 3, generator=g, dtype=torch.float64)
    ref_leaves = [sh.clone().requires_grad_(True), dirs.clone().requires_grad_(True)]
    ref = eval_sh(3, *ref_leaves)
    (ref * w).sum().backward()
    ref_g0, ref_gN, ref_gd = ref_leaves[0].grad[:, :1], ref_leaves[0].grad[:, 1:], ref_leaves[1].grad
    rest_t = sh[:, 1:].transpose(1, 2).contiguous().transpose(1, 2)  # same values, bands not dense
    assert rest_t.stride(1) != 3
    for train0, trainN in ((False, False), (True, False), (False, True), (True, True)):
        sh0 = sh[:, :1].clone().requires_grad_(train0)
        rest = rest_t.clone(memory_format=torch.preserve_format).requires_grad_(trainN)
        d = dirs.clone().requires_grad_(True)
        out = eval_sh_fast(3, sh0, d, sh_rest=rest)
        (out * w).sum().backward()
        assert torch.allclose(out, ref.detach(), rtol=0, atol=1e-12)
        assert torch.allclose(d.grad, ref_gd, rtol=0, atol=1e-12)
        assert (sh0.grad is not None) == train0 and (rest.grad is not None) == trainN
        if train0:
            assert torch.allclose(sh0.grad, ref_g0, rtol=0, atol=1e-12)
        if trainN:
            assert torch.allclose(rest.grad, ref_gN, rtol=0, atol=1e-12)
    sh0 = sh[:5, :1].clone().requires_grad_(True)
    rest = sh[:5, 1:].clone().requires_grad_(True)
    d5 = dirs[:5].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b, d: eval_sh_fast(3, a, d, sh_rest=b), (sh0, rest, d5),
                                    eps=1e-6, atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="DC band"):
        eval_sh_fast(3, sh, dirs, sh_rest=rest)


def test_cpp_sh_kernel_wrappers_refuse_what_the_kernel_would_misread(cpp_kernel):
    from splat import _cpu_kernel
    from splat.sh import _BASIS_CONSTANTS, NORMALIZE_EPS

    sh = torch.randn(10, 4, 3)
    dirs = torch.randn(10, 3)
    kw = {"basis_constants": _BASIS_CONSTANTS, "norm_eps": NORMALIZE_EPS}
    with pytest.raises(ValueError, match="needs 9 bases"):
        _cpu_kernel.sh_forward(2, sh[:, :1], sh[:, 1:], dirs, **kw)
    with pytest.raises(ValueError, match="dirs"):
        _cpu_kernel.sh_forward(1, sh[:, :1], sh[:, 1:], dirs[:9], **kw)
    with pytest.raises(ValueError, match="g_shN"):
        _cpu_kernel.sh_backward(1, sh[:, :1], sh[:, 1:], dirs, torch.ones(10, 3), g_shN=torch.empty(10, 4, 3), **kw)
    # an empty model is fine, whatever torch says its strides are
    empty = torch.empty(0, 16, 3)
    assert _cpu_kernel.sh_forward(3, empty[:, :1], empty[:, 1:], torch.empty(0, 3), **kw).shape == (0, 3)
