"""`.splat` / `.spz` export: byte layout against slow per-Gaussian references, and PLY -> format -> back
round trips within each format's quantisation (each tolerance derived next to its assertion)."""

from __future__ import annotations

import gzip
import struct

import numpy as np
import pytest
import torch

from mvgeo.common.errors import InputError
from mvgeo.transforms import R_from_quat
from splat import export
from splat.export import (
    SH_C0,
    SPLAT_BYTES_PER_GAUSSIAN,
    SPZ_COLOR_SCALE,
    SPZ_MAGIC,
    read_splat,
    read_spz,
    read_spz_header,
    splat_bytes,
    splat_importance_order,
    write_splat,
    write_spz,
)
from splat.gaussian_model import GaussianModel
from splat.ply import read_gaussian_ply, write_gaussian_ply
from splat.sh import eval_sh
from tests.splat.scenes import random_scene


def _model(n: int, seed: int, sh_degree: int = 3, spread: float = 0.6) -> GaussianModel:
    p = random_scene(n, seed=seed, dtype=torch.float32, sh_degree=sh_degree, spread=spread)
    sh = p["sh"]
    return GaussianModel(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], sh[:, :1], sh[:, 1:])


def _np(model: GaussianModel) -> dict[str, np.ndarray]:
    return {k: v.detach().double().numpy() for k, v in model.params_dict().items()}


def _via_ply(model: GaussianModel, tmp_path) -> GaussianModel:
    write_gaussian_ply(tmp_path / "m.ply", model)
    return read_gaussian_ply(tmp_path / "m.ply")


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def _unit(q):
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


# ------------------------------------------------------------------------------------------ .splat


def _splat_record_reference(m: dict[str, np.ndarray], i: int) -> bytes:
    """One Gaussian as antimatter15's convert.py lays it out (with rounding instead of truncation)."""
    pos = struct.pack("<3f", *m["means"][i])
    scale = struct.pack("<3f", *np.exp(m["log_scales"][i]).astype(np.float32))
    rgb = [0.5 + SH_C0 * c for c in m["sh0"][i, 0]]
    rgba = [*rgb, 1.0 / (1.0 + np.exp(-m["opacity_logits"][i]))]
    col = bytes(int(min(max(round(v * 255.0), 0), 255)) for v in rgba)
    q = m["quats"][i] / np.linalg.norm(m["quats"][i])
    rot = bytes(int(min(max(round(v * 128.0 + 128.0), 0), 255)) for v in q)
    return pos + scale + col + rot


def test_splat_is_32_bytes_per_gaussian_in_the_reference_layout(tmp_path):
    model = _model(57, seed=1)
    write_splat(tmp_path / "m.splat", model)
    data = (tmp_path / "m.splat").read_bytes()
    assert len(data) == SPLAT_BYTES_PER_GAUSSIAN * 57
    m = {k: v.detach().float().numpy() for k, v in model.params_dict().items()}
    # convert.py's order: argsort(-exp(s0 + s1 + s2) / (1 + exp(-opacity)))
    s = m["log_scales"].astype(np.float64)
    order = np.argsort(-np.exp(s[:, 0] + s[:, 1] + s[:, 2]) / (1 + np.exp(-m["opacity_logits"].astype(np.float64))),
                       kind="stable")
    np.testing.assert_array_equal(splat_importance_order(m["log_scales"], m["opacity_logits"]), order)
    expected = b"".join(_splat_record_reference(m, int(i)) for i in order)
    # float32 exp may differ from the reference's in the last bit: compare the byte records field by field
    got = np.frombuffer(data, np.uint8).reshape(57, 32)
    ref = np.frombuffer(expected, np.uint8).reshape(57, 32)
    np.testing.assert_array_equal(got[:, :12], ref[:, :12])  # positions: exact
    np.testing.assert_allclose(got[:, 12:24].copy().view("<f4"), ref[:, 12:24].copy().view("<f4"), rtol=1e-6)
    np.testing.assert_array_equal(got[:, 24:], ref[:, 24:])  # colour, alpha, rotation bytes


def test_splat_round_trip_from_ply_within_byte_quantisation(tmp_path):
    model = _via_ply(_model(300, seed=2), tmp_path)
    write_splat(tmp_path / "m.splat", model)
    back = read_splat(tmp_path / "m.splat")
    assert back.num_gaussians == 300 and back.sh_degree_max == 0
    m, b = _np(model), _np(back)
    order = splat_importance_order(m["log_scales"], m["opacity_logits"])
    m = {k: v[order] for k, v in m.items()}
    np.testing.assert_array_equal(b["means"], m["means"])  # float32 both ways
    np.testing.assert_allclose(b["log_scales"], m["log_scales"], atol=1e-5)  # float32 exp then log
    # Colour and alpha: one byte over [0, 1], rounded: |error| <= 0.5 / 255 (+ float32 slack).
    rgb, rgb_back = 0.5 + SH_C0 * m["sh0"][:, 0], 0.5 + SH_C0 * b["sh0"][:, 0]
    assert rgb.min() > 0 and rgb.max() < 1  # the scene's colours are inside the byte range
    assert np.abs(rgb_back - rgb).max() <= 0.5 / 255 + 1e-6
    assert np.abs(_sigmoid(b["opacity_logits"]) - _sigmoid(m["opacity_logits"])).max() <= 0.5 / 255 + 1e-6
    # Rotation: each component of the unit quaternion is rounded to 1/128 (error <= 0.5/128, <= 1/128 where
    # +1 clips to 255), so |d - q|_2 <= sqrt((1/128)^2 + 3 (0.5/128)^2) = 1.33/128, and renormalising at most
    # doubles a vector's error: |d/|d| - q| <= 2.65/128 per component.
    q, d = _unit(m["quats"]), _unit(b["quats"])
    assert np.abs(d - q).max() <= 2.65 / 128


def test_read_splat_rejects_a_partial_record(tmp_path):
    (tmp_path / "bad.splat").write_bytes(b"\0" * 33)
    with pytest.raises(InputError, match="multiple of 32"):
        read_splat(tmp_path / "bad.splat")


# -------------------------------------------------------------------------------------------- .spz


def test_spz_header_counts_the_gaussians(tmp_path):
    write_spz(tmp_path / "m.spz", _model(123, seed=3))
    raw = (tmp_path / "m.spz").read_bytes()
    assert raw[:2] == b"\x1f\x8b"  # a gzip stream
    magic, version, n, degree, bits, flags, reserved = struct.unpack_from("<IIIBBBB", gzip.decompress(raw))
    assert (magic, version, n, degree, bits, flags, reserved) == (SPZ_MAGIC, 3, 123, 3, 12, 0, 0)
    assert gzip.decompress(raw)[:4] == b"NGSP"
    h = read_spz_header(tmp_path / "m.spz")
    assert (h.num_points, h.sh_degree, h.fractional_bits) == (123, 3, 12)
    # 9 + 1 + 3 + 3 + 4 + 45 bytes per Gaussian after the 16-byte header
    assert len(gzip.decompress(raw)) == 16 + 123 * (9 + 1 + 3 + 3 + 4 + 45)


def _pack_smallest_three_reference(q_xyzw) -> bytes:
    """Niantic's packQuaternionSmallestThree, one quaternion, plain Python integers."""
    q = [float(v) for v in q_xyzw]
    i_largest = max(range(4), key=lambda i: abs(q[i]))
    negate = q[i_largest] < 0
    comp = i_largest
    for i in range(4):
        if i != i_largest:
            negbit = int((q[i] < 0) != negate)
            mag = int((2 ** 9 - 1) * (abs(q[i]) / np.sqrt(0.5)) + 0.5)
            comp = (comp << 10) | (negbit << 9) | mag
    return struct.pack("<I", comp)


def test_spz_smallest_three_matches_the_reference_packing(rng):
    q = _unit(rng.normal(size=(200, 4)))
    packed = export._pack_quats_smallest_three(q)
    expected = b"".join(_pack_smallest_three_reference(v) for v in q)
    assert packed.tobytes() == expected
    back = export._unpack_quats_smallest_three(packed)
    # Each stored component is rounded to sqrt(1/2)/511 (error <= e = 0.5 sqrt(1/2)/511); the largest one,
    # recomputed from unit norm, errs by <= 3e (each |q_i| <= |q_largest|). Compare up to the sign of q.
    e = 0.5 * np.sqrt(0.5) / 511
    sign = np.sign(np.sum(back * q, axis=1, keepdims=True))
    assert np.abs(back * sign - q).max() <= 3 * e + 1e-9


def test_spz_round_trip_from_ply_within_its_quantisation(tmp_path):
    model = _via_ply(_model(400, seed=4), tmp_path)
    write_spz(tmp_path / "m.spz", model)
    back = read_spz(tmp_path / "m.spz")
    m, b = _np(model), _np(back)
    assert back.num_gaussians == 400 and back.sh_degree_max == 3
    # 24-bit fixed point with 12 fractional bits, rounded: |error| <= 2^-13 (+ float32 slack).
    assert np.abs(b["means"] - m["means"]).max() <= 2.0 ** -13 + 1e-6
    # log scale in 1/16 steps, rounded: <= 1/32.
    assert np.abs(b["log_scales"] - m["log_scales"]).max() <= 1 / 32 + 1e-6
    # alpha byte, rounded: <= 0.5/255 in opacity.
    assert np.abs(_sigmoid(b["opacity_logits"]) - _sigmoid(m["opacity_logits"])).max() <= 0.5 / 255 + 1e-6
    # DC byte holds f_dc * 0.15 * 255: <= 0.5 / (0.15 * 255) in f_dc.
    assert np.abs(b["sh0"] - m["sh0"]).max() <= 0.5 / (SPZ_COLOR_SCALE * 255) + 1e-6
    # SH: round(x * 128), snapped to multiples of 8 (degree 1) or 16 (degrees 2, 3): <= 4.5/128, 8.5/128.
    assert np.abs(b["shN"][:, :3] - m["shN"][:, :3]).max() <= 4.5 / 128 + 1e-6
    assert np.abs(b["shN"][:, 3:] - m["shN"][:, 3:]).max() <= 8.5 / 128 + 1e-6
    # rotation: see test_spz_smallest_three_matches_the_reference_packing (3e), plus float32.
    q, d = _unit(m["quats"]), _unit(b["quats"])
    sign = np.sign(np.sum(d * q, axis=1, keepdims=True))
    assert np.abs(d * sign - q).max() <= 3 * 0.5 * np.sqrt(0.5) / 511 + 1e-6


def test_spz_axis_mirror_is_a_rotation_of_the_scene():
    """The RDF -> RUB mirror (y, z negated) must map each Gaussian's rotation to F R F and its SH colour
    function to c(F d) = c(d): what a viewer sees from the mirrored direction is what we saw."""
    g = torch.Generator().manual_seed(5)
    flip = np.diag([1.0, -1.0, -1.0])
    q = _unit(np.random.default_rng(5).normal(size=(20, 4)))
    q_rub = np.concatenate([q[:, :1], q[:, 1:] * export._P_FLIP_RDF_RUB], axis=1)
    for a, b in zip(q, q_rub, strict=True):
        np.testing.assert_allclose(R_from_quat(b), flip @ R_from_quat(a) @ flip, atol=1e-12)
    sh = torch.randn(50, 16, 3, generator=g, dtype=torch.float64)
    dirs = torch.randn(50, 3, generator=g, dtype=torch.float64)
    sh_rub = sh.clone()
    sh_rub[:, 1:] *= torch.as_tensor(export._SH_FLIP_RDF_RUB, dtype=torch.float64)[:, None]
    dirs_rub = dirs * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    torch.testing.assert_close(eval_sh(3, sh_rub, dirs_rub), eval_sh(3, sh, dirs))


def test_spz_lowers_fractional_bits_for_a_large_scene(tmp_path):
    model = _model(30, seed=6, spread=5000.0)  # |x| up to 5000 > 2^11: 12 fractional bits would overflow
    write_spz(tmp_path / "m.spz", model)
    h = read_spz_header(tmp_path / "m.spz")
    assert h.fractional_bits == 10  # 5000 * 2^10 < 2^23 - 1 < 5000 * 2^11
    back = read_spz(tmp_path / "m.spz")
    assert np.abs(_np(back)["means"] - _np(model)["means"]).max() <= 2.0 ** -11 + 1e-3


def test_spz_reader_rejects_other_files(tmp_path):
    (tmp_path / "plain.spz").write_bytes(b"not gzip")
    with pytest.raises(InputError, match="gzip"):
        read_spz(tmp_path / "plain.spz")
    (tmp_path / "magic.spz").write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x1234, 3, 0, 0, 12, 0, 0)))
    with pytest.raises(InputError, match="magic"):
        read_spz_header(tmp_path / "magic.spz")
    (tmp_path / "short.spz").write_bytes(gzip.compress(struct.pack("<IIIBBBB", SPZ_MAGIC, 3, 10, 0, 12, 0, 0)))
    with pytest.raises(InputError, match="shorter"):
        read_spz(tmp_path / "short.spz")


def test_splat_bytes_refuses_non_finite_models():
    model = _model(4, seed=7)
    with torch.no_grad():
        model.means[0, 0] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        splat_bytes(model)


def test_splat_export_cli_writes_each_format(tmp_path):
    from splat.cli import main

    model = _model(77, seed=8)
    write_gaussian_ply(tmp_path / "point_cloud.ply", model)
    src = str(tmp_path / "point_cloud.ply")
    assert main(["export", src, "--format", "splat", "--out", str(tmp_path / "a.splat")]) == 0
    assert (tmp_path / "a.splat").stat().st_size == 32 * 77
    assert main(["export", src, "--out", str(tmp_path / "a.spz")]) == 0  # format from the suffix
    assert read_spz_header(tmp_path / "a.spz").num_points == 77
    assert main(["export", src, "--format", "ply", "--out", str(tmp_path / "b.ply")]) == 0
    np.testing.assert_array_equal(_np(read_gaussian_ply(tmp_path / "b.ply"))["means"], _np(model)["means"])
    # an existing file is kept unless --overwrite; an unknown suffix needs --format
    assert main(["export", src, "--out", str(tmp_path / "a.splat")]) == 2
    assert main(["export", src, "--out", str(tmp_path / "a.splat"), "--overwrite"]) == 0  # written by export
    (tmp_path / "mine.splat").write_bytes(b"user data")  # not written by export: never replaced
    assert main(["export", src, "--out", str(tmp_path / "mine.splat"), "--overwrite"]) == 2
    assert (tmp_path / "mine.splat").read_bytes() == b"user data"
    (tmp_path / "a.splat").write_bytes(b"edited")  # changed since: kept
    assert main(["export", src, "--out", str(tmp_path / "a.splat"), "--overwrite"]) == 2
    assert (tmp_path / "a.splat").read_bytes() == b"edited"
    assert main(["export", src, "--out", str(tmp_path / "a.bin")]) == 2
    assert main(["export", src, "--format", "splat", "--out", str(tmp_path / "x.ply")]) == 2  # .splat in a .ply
    assert not (tmp_path / "x.ply").exists()
    assert main(["export", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "c.splat")]) == 2
    assert not (tmp_path / "c.splat").exists()


def test_spz_keeps_the_finest_fixed_point_a_coordinate_fits_as_rounded():
    # 24-bit positions hold round(p * 2**bits) up to 2**23 - 1: a coordinate of exactly that many 12-bit steps fits
    # 12 bits (before: one bit fewer, 2.4e-4 off); half a step beyond it does not.
    edge = 8388607 / 4096
    assert export._spz_fractional_bits(np.array([[edge, 0.0, 0.0]]), 12) == 12
    assert export._spz_fractional_bits(np.array([[edge + 0.6 / 4096, 0.0, 0.0]]), 12) == 11
    assert export._spz_fractional_bits(np.array([[8388607.0, 0.0, 0.0]]), 12) == 0
    with pytest.raises(InputError, match="24-bit"):
        export._spz_fractional_bits(np.array([[8388607.6, 0.0, 0.0]]), 12)


def test_splat_refuses_scales_beyond_float32():
    m = _model(4, seed=2)
    with torch.no_grad():
        m.log_scales[1, 0] = 89.0  # exp(89) overflows float32: the file would hold inf
    with pytest.raises(InputError, match="beyond float32"):
        splat_bytes(m)
