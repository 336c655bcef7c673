"""The C++ tile binning (`csrc/tiles.cpp`) gives exactly the torch reference's lists, and both match a
slow brute-force construction (loop over every tile and pixel centre, sort by (depth, index))."""

from __future__ import annotations

import pytest
import torch

from splat.projection import project_gaussians
from splat.tiles import bin_gaussians
from tests.splat.scenes import activated, random_camera, random_scene

pytestmark = pytest.mark.needs_cpp_kernel


def _brute_force_lists(means2d, extents, depths, visible, width, height, tile_size):
    """Per tile: the visible Gaussians with a pixel centre inside their box, by (depth, index)."""
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    lists = []
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            members = []
            for g in range(means2d.shape[0]):
                if not bool(visible[g]):
                    continue
                u, v = float(means2d[g, 0]), float(means2d[g, 1])
                ex, ey = float(extents[g, 0]), float(extents[g, 1])
                cols = [c + 0.5 for c in range(tx * tile_size, min((tx + 1) * tile_size, width))]
                rows = [r + 0.5 for r in range(ty * tile_size, min((ty + 1) * tile_size, height))]
                if any(u - ex <= c <= u + ex for c in cols) and any(v - ey <= r <= v + ey for r in rows):
                    members.append(g)
            members.sort(key=lambda g: (float(depths[g]), g))
            lists.append(members)
    return lists


def _as_lists(bins):
    offs = bins.tile_offsets.tolist()
    ids = bins.gaussian_ids.tolist()
    return [ids[offs[k]:offs[k + 1]] for k in range(len(offs) - 1)]


def _projected(n, width, height, seed, dtype):
    cam, K = random_camera(width, height, seed=seed, dtype=dtype)
    means, quats, scales, opac, _ = activated(random_scene(n, seed=seed + 1, dtype=dtype, spread=1.0))
    p = project_gaussians(means, quats, scales, opac, cam, K, width, height)
    return p.means2d.detach(), p.extents_px, p.depths.detach(), p.visible


@pytest.mark.parametrize(("width", "height", "tile_size", "dtype"),
                         [(45, 38, 8, torch.float64), (64, 48, 16, torch.float32), (17, 5, 16, torch.float32)])
def test_cpp_bins_equal_torch_and_brute_force(width, height, tile_size, dtype):
    m, e, d, vis = _projected(90, width, height, seed=width, dtype=dtype)
    # Edge cases: a box covering the whole image, one exactly on a pixel centre boundary, one just outside
    # the image, an invisible one with a huge box, and depth ties (the index breaks them).
    m = torch.cat([m, torch.tensor([[width / 2, height / 2], [3.5, 2.5], [-2.0, 1.0], [5.0, 5.0],
                                    [width - 0.2, height - 0.2], [width - 0.2, 0.3]], dtype=dtype)])
    e = torch.cat([e, torch.tensor([[1e4, 1e4], [1.0, 1.0], [1.9, 3.0], [1e4, 1e4],
                                    [0.5, 0.5], [0.5, 0.5]], dtype=dtype)])
    d = torch.cat([d, torch.tensor([2.0, 3.0, 1.0, 0.5, 2.0, 2.0], dtype=dtype)])
    vis = torch.cat([vis, torch.tensor([True, True, True, False, True, True])])
    expected = _brute_force_lists(m, e, d, vis, width, height, tile_size)
    for backend in ("torch", "cpp"):
        bins = bin_gaussians(m, e, d, vis, width, height, tile_size=tile_size, backend=backend)
        assert bins.gaussian_ids.dtype == torch.int64 and bins.tile_offsets.dtype == torch.int64
        assert _as_lists(bins) == expected, backend
    assert any(len(lst) > 0 for lst in expected)


def test_cpp_bins_equal_torch_on_a_large_scene():
    m, e, d, vis = _projected(20_000, 160, 120, seed=3, dtype=torch.float32)
    ref = bin_gaussians(m, e, d, vis, 160, 120, backend="torch")
    got = bin_gaussians(m, e, d, vis, 160, 120, backend="cpp")
    assert ref.gaussian_ids.numel() > 20_000
    assert torch.equal(ref.tile_offsets, got.tile_offsets)
    assert torch.equal(ref.gaussian_ids, got.gaussian_ids)


def test_cpp_bins_with_nothing_visible():
    m, e, d, vis = _projected(10, 32, 32, seed=4, dtype=torch.float32)
    bins = bin_gaussians(m, e, d, torch.zeros_like(vis), 32, 32, backend="cpp")
    assert bins.gaussian_ids.numel() == 0
    assert bins.tile_offsets.shape == (5,) and (bins.tile_offsets == 0).all()
