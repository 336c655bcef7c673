"""GaussianModel initialisation and the 3DGS PLY format."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData

from mvgeo.common.errors import InputError
from splat.gaussian_model import GaussianModel
from splat.ply import read_gaussian_ply, write_gaussian_ply
from splat.sh import SH_C0


def test_init_from_points(rng):
    xyz = rng.normal(size=(50, 3))
    rgb = rng.integers(0, 256, size=(50, 3), dtype=np.uint8)
    m = GaussianModel.from_points(xyz, rgb, sh_degree=2)
    assert m.num_gaussians == 50 and m.sh_degree_max == 2 and m.shN.shape == (50, 8, 3)
    # colour -> SH DC: rendering the DC term alone gives the colour back
    np.testing.assert_allclose((m.sh0[:, 0].detach().numpy() * SH_C0 + 0.5), rgb / 255.0, atol=1e-6)
    np.testing.assert_allclose(m.opacities.detach().numpy(), 0.1, rtol=1e-6)
    # scale = RMS distance to the 3 nearest neighbours (brute force reference)
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    d.sort(axis=1)
    expected = np.sqrt(np.mean(d[:, 1:4] ** 2, axis=1))
    np.testing.assert_allclose(m.scales.detach().numpy()[:, 0], expected, rtol=1e-5)
    assert (m.quats.detach().numpy() == [1, 0, 0, 0]).all()


def test_init_errors():
    with pytest.raises(InputError):
        GaussianModel.from_points(np.zeros((1, 3)), np.zeros((1, 3), np.uint8))
    with pytest.raises(InputError):
        GaussianModel.from_points(np.full((5, 3), np.nan), np.zeros((5, 3), np.uint8))
    with pytest.raises(InputError):
        GaussianModel.from_points(np.zeros((5, 3)), np.zeros((4, 3), np.uint8))


@pytest.mark.parametrize("degree", [0, 3])
def test_ply_round_trip_exact(tmp_path, degree):
    g = torch.Generator().manual_seed(1)
    n, k = 17, (degree + 1) ** 2
    m = GaussianModel(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g), torch.randn(n, 3, generator=g),
                      torch.randn(n, generator=g), torch.randn(n, 1, 3, generator=g),
                      torch.randn(n, k - 1, 3, generator=g))
    path = tmp_path / "point_cloud.ply"
    write_gaussian_ply(path, m)
    back = read_gaussian_ply(path)
    for name, p in m.params_dict().items():
        assert torch.equal(getattr(back, name), p), name  # float32 in, float32 out: bit-exact
    # Layout read with plyfile alone: property names/order and channel-major f_rest.
    v = PlyData.read(str(path))["vertex"]
    names = [p.name for p in v.properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(names) == 17 + 3 * (k - 1)
    if degree:
        # f_rest_{c * (K-1) + j} is channel c of basis j + 1
        assert v["f_rest_0"][3] == m.shN[3, 0, 0].item()
        assert v[f"f_rest_{k - 1}"][3] == m.shN[3, 0, 1].item()
        assert v[f"f_rest_{k}"][3] == m.shN[3, 1, 1].item()
    assert v["rot_0"][5] == m.quats[5, 0].item()  # rot is wxyz


def test_ply_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_gaussian_ply(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(InputError):
        read_gaussian_ply(bad)
