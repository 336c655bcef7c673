"""The C++ compositor against the torch compositor on raw 2D Gaussians (no projection).

The C++ kernel visits, per tile, only the pixel box of each Gaussian inside which its
sigma can pass the 1/255 test, each of the box's rows only over the span of the ellipse,
in groups of four pixels; the torch path evaluates every (pixel, Gaussian) pair of
the tile. Random conics up to condition number ~1e8 and centres off the image check
that the box never drops a contribution, and that results do not depend on the thread
count.
"""

from __future__ import annotations

import pytest
import torch

from splat.composite import composite_tiles
from splat.tiles import bin_gaussians

pytestmark = pytest.mark.needs_cpp_kernel  # every test here compares the C++ kernel


def _random_2d(n, width, height, seed, dtype, *, ill_conditioned):
    g = torch.Generator().manual_seed(seed)
    means2d = torch.rand(n, 2, generator=g, dtype=dtype) * torch.tensor([width + 30.0, height + 30.0], dtype=dtype) - 15
    angle = torch.rand(n, generator=g, dtype=dtype) * 3.1416
    l1 = 0.3 + torch.exp(torch.rand(n, generator=g, dtype=dtype) * 6 - 2)  # eigenvalues of the 2D covariance, px^2
    l2 = 0.3 + torch.exp(torch.rand(n, generator=g, dtype=dtype) * (18 if ill_conditioned else 6) - 2)
    c, s = torch.cos(angle), torch.sin(angle)
    sxx, syy, sxy = l1 * c * c + l2 * s * s, l1 * s * s + l2 * c * c, (l1 - l2) * c * s
    det = sxx * syy - sxy * sxy
    conics = torch.stack([syy / det, -sxy / det, sxx / det], -1)
    opac = torch.rand(n, generator=g, dtype=dtype)
    opac[:4] = 1.0  # clamped at 0.99
    opac[4:6] = 0.0
    colors = torch.rand(n, 4, generator=g, dtype=dtype)
    depths = torch.rand(n, generator=g, dtype=dtype)
    # Binning box from the covariance (as projection does), so tiles hold every candidate.
    r = torch.sqrt(2 * torch.log(torch.clamp(opac, min=1e-30) * 255).clamp(min=0))
    extents = torch.stack([r * sxx.sqrt(), r * syy.sqrt()], -1)
    visible = opac > 1 / 255
    return means2d, conics, colors, opac, extents, depths, visible


def _render(args, width, height, backend, num_threads=None):
    means2d, conics, colors, opac, extents, depths, visible = args
    leaves = [t.clone().requires_grad_(True) for t in (means2d, conics, colors, opac)]
    bins = bin_gaussians(means2d, extents, depths, visible, width, height)
    acc, trans = composite_tiles(*leaves, bins, width, height, backend=backend, num_threads=num_threads)
    g = torch.Generator().manual_seed(1)
    loss = (acc * torch.randn(acc.shape, generator=g, dtype=acc.dtype)).sum() \
        + (trans * torch.randn(trans.shape, generator=g, dtype=acc.dtype)).sum()
    loss.backward()
    return [acc.detach(), trans.detach()] + [t.grad for t in leaves]


@pytest.mark.parametrize("ill_conditioned", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpp_matches_torch_compositor(dtype, ill_conditioned):
    width, height = 45, 35
    args = _random_2d(150, width, height, seed=2, dtype=dtype, ill_conditioned=ill_conditioned)
    fast = _render(args, width, height, "cpp")
    ref = _render(args, width, height, "torch")
    # float64: same arithmetic up to summation order (observed ~1e-13). float32: accumulated
    # rounding over up to ~150 layers per pixel; 1e-4 relative is far below a dropped
    # contribution (>= 1/255 of a colour).
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    names = ["accum", "transmittance", "d means2d", "d conics", "d colors", "d opacities"]
    for name, a, b in zip(names, fast, ref, strict=True):
        scale = b.abs().max().clamp(min=1.0)
        assert torch.allclose(a, b, rtol=0, atol=tol * scale), (name, float((a - b).abs().max()))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_thin_tilted_gaussians_lose_no_pixel(dtype):
    # The kernel narrows each row of a Gaussian's box to the row's span of its ellipse, computed in double with a
    # margin for the rounding of det = a c - b^2, which is worst for thin Gaussians (condition numbers here up to
    # ~1e9 in float64). Tilted near 45 degrees, their spans are far narrower than their boxes. A pixel dropped at
    # a rim would lose at least 1/255 of a colour (a span shrunk by 0.05 px fails here at 4e-3).
    width, height = 48, 40
    g = torch.Generator().manual_seed(7)
    n = 120
    means2d = torch.rand(n, 2, generator=g, dtype=dtype) * torch.tensor([width, height], dtype=dtype)
    angle = 0.785 + 0.3 * (torch.rand(n, generator=g, dtype=dtype) - 0.5)
    l1 = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=dtype)
    # Up to e^20 px^2 in float64. float32 stops at e^12 (condition ~5e5): beyond it sigma's float32 rounding
    # differs between the two paths' expressions by more than the 1/255 threshold, in either kernel version.
    top = 20 if dtype == torch.float64 else 12
    l2 = torch.exp(torch.rand(n, generator=g, dtype=dtype) * (top - 2) + 2)
    c, s = torch.cos(angle), torch.sin(angle)
    sxx, syy, sxy = l1 * c * c + l2 * s * s, l1 * s * s + l2 * c * c, (l1 - l2) * c * s
    det = sxx * syy - sxy * sxy
    conics = torch.stack([syy / det, -sxy / det, sxx / det], -1)
    opac = 0.2 + 0.7 * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 4, generator=g, dtype=dtype)
    depths = torch.rand(n, generator=g, dtype=dtype)
    r = torch.sqrt(2 * torch.log(opac * 255))
    extents = torch.stack([r * sxx.sqrt(), r * syy.sqrt()], -1)
    args = (means2d, conics, colors, opac, extents, depths, opac > 1 / 255)
    fast = _render(args, width, height, "cpp")
    ref = _render(args, width, height, "torch")
    tol = 1e-9 if dtype == torch.float64 else 1e-4  # as in test_cpp_matches_torch_compositor
    names = ["accum", "transmittance", "d means2d", "d conics", "d colors", "d opacities"]
    for name, a, b in zip(names, fast, ref, strict=True):
        scale = b.abs().max().clamp(min=1.0)
        assert torch.allclose(a, b, rtol=0, atol=tol * scale), (name, float((a - b).abs().max()))


def _one_gaussian_args(mean, conic, opacity, colour, dtype):
    means2d = torch.tensor([mean], dtype=dtype)
    conics = torch.tensor([conic], dtype=dtype)
    a, b, c = conic
    det = a * c - b * b
    sxx, syy = c / det, a / det  # the covariance's diagonal
    r = (2 * torch.log(torch.tensor(opacity * 255.0, dtype=torch.float64))).sqrt()
    extents = torch.tensor([[float(r * sxx**0.5), float(r * syy**0.5)]], dtype=dtype)
    opac = torch.tensor([opacity], dtype=dtype)
    colors = torch.tensor([colour], dtype=dtype)
    return means2d, conics, colors, opac, extents, torch.zeros(1, dtype=dtype), opac > 1 / 255


@pytest.mark.parametrize(("conic", "dtype"), [
    ((1e-18, 0.0, 1.0), torch.float32),  # a horizontal band: its row spans are wider than int32's range
    ((1e-20, 0.0, 1.0), torch.float64),
    ((1e-4, -1e-4 * (1 - 1e-15), 1e-4), torch.float64),  # a 45-degree streak, det ~1e-23: a huge span margin
])
def test_very_wide_or_nearly_singular_gaussians_render(conic, dtype):
    width, height = 32, 32
    args = _one_gaussian_args((16.3, 15.7), conic, 0.8, (0.9, 0.5, 0.2, 1.0), dtype)
    fast = _render(args, width, height, "cpp")
    ref = _render(args, width, height, "torch")
    assert float(ref[0].sum()) > 100  # the Gaussian covers much of the image
    for name, a, b in zip(["accum", "transmittance"], fast[:2], ref[:2], strict=True):
        assert torch.allclose(a, b, rtol=0, atol=1e-5), (name, float((a - b).abs().max()))


def test_a_non_finite_colour_stays_in_the_pixels_its_gaussian_reaches():
    # A small Gaussian in front of a large one: the pixels it reaches are those whose colour changes with its
    # colour; with a NaN colour exactly those pixels are NaN (the kernel evaluates four pixels at a time, and the
    # others must not pick up 0 * NaN).
    width, height = 24, 20
    dtype = torch.float32
    big = _one_gaussian_args((12.0, 10.0), (0.01, 0.0, 0.01), 0.5, (0.3, 0.3, 0.3, 1.0), dtype)

    def render(colour):
        small = _one_gaussian_args((6.4, 5.6), (2.0, 0.3, 1.5), 0.9, colour, dtype)
        args = [torch.cat([s, b]) for s, b in zip(small[:6], big[:6], strict=True)] + [torch.cat([small[6], big[6]])]
        args[5] = torch.tensor([0.0, 1.0], dtype=dtype)  # the small one in front
        bins = bin_gaussians(args[0], args[4], args[5], args[6], width, height)
        acc, _ = composite_tiles(*args[:4], bins, width, height, backend="cpp")
        return acc[..., 0]

    reached = render((0.0, 0.0, 0.0, 0.0)) != render((1.0, 1.0, 1.0, 1.0))
    assert 1 <= int(reached.sum()) <= 30
    assert torch.equal(render((float("nan"), 0.0, 0.0, 0.0)).isnan(), reached)


def test_cpp_result_independent_of_thread_count():
    width, height = 70, 50
    args = _random_2d(400, width, height, seed=5, dtype=torch.float32, ill_conditioned=True)
    one = _render(args, width, height, "cpp", num_threads=1)
    three = _render(args, width, height, "cpp", num_threads=3)
    for a, b in zip(one, three, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gather_is_index_add_into_zeros(threads, dtype, cpp_kernel):
    """The backward's per-Gaussian sums (`_cpu_kernel.gather`) are the numbers of one `index_add_` of the rows
    into zeros (the same additions in the same order), split into the four gradients, for any thread count;
    Gaussians without an intersection get zeros."""
    from splat import _cpu_kernel

    g = torch.Generator().manual_seed(threads)
    n, n_rows, C = 20000, 90000, 4
    ids = torch.randint(0, n - 100, (n_rows,), generator=g)  # the last 100 Gaussians are never hit
    rows = torch.randn(n_rows, 6 + C, generator=g, dtype=dtype) * torch.rand(n_rows, 1, generator=g, dtype=dtype) * 1e3
    ref = torch.zeros(n, 6 + C, dtype=dtype).index_add_(0, ids, rows)
    g_m, g_c, g_o, g_col = _cpu_kernel.gather(ids, rows, n, num_threads=threads)
    assert torch.equal(g_m, ref[:, :2]) and torch.equal(g_c, ref[:, 2:5])
    assert torch.equal(g_o, ref[:, 5]) and torch.equal(g_col, ref[:, 6:])
    assert all(t.is_contiguous() for t in (g_m, g_c, g_o, g_col))
    assert (g_col[-100:] == 0).all()
    with pytest.raises(ValueError, match=r"\[0, 20000\)"):
        _cpu_kernel.gather(torch.full((n_rows,), n), rows, n)
    with pytest.raises(ValueError, match="int64 ids"):
        _cpu_kernel.gather(ids.to(torch.int32), rows, n)
