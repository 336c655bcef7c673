"""Real SH basis: orthonormal on the sphere; DC round trip."""

from __future__ import annotations

import math

import torch

from splat.sh import eval_sh, rgb_to_sh_dc, sh_basis, sh_dc_to_rgb


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
