"""Web splat formats: antimatter15's `.splat` and Niantic's `.spz` (writers and readers).

`.splat` (the layout of antimatter15/splat's `convert.py` and viewer): no header, 32 bytes per
Gaussian, little-endian, sorted by importance `exp(sum(log_scales)) * sigmoid(opacity)`,
largest first:

    offset  0: position     3 x float32 (world units)
    offset 12: scale        3 x float32 (linear standard deviations, `exp(log_scales)`)
    offset 24: RGBA         4 x uint8: RGB = 0.5 + SH_C0 * f_dc, A = sigmoid(opacity), times 255
    offset 28: rotation     4 x uint8: unit quaternion wxyz, `q * 128 + 128` clipped to [0, 255]

Only the SH DC term survives (no view-dependent colour). We round to the nearest byte where the
reference truncates; readers decode both the same way (`byte / 255`, `(byte - 128) / 128`).

`.spz` (nianticlabs/spz, `load-spz.cc`): a gzip stream of a 16-byte header
`magic 0x5053474e ("NGSP"), version u32, num_points u32, sh_degree u8, fractional_bits u8,
flags u8, reserved u8`, then per attribute, all Gaussians in turn: positions (3 x 24-bit signed
fixed point, `round(p * 2**fractional_bits)`), alphas (`sigmoid(opacity) * 255`), colours
(`f_dc * 0.15 * 255 + 127.5`), scales (`(log_scale + 10) * 16`), rotations, SH coefficients
(coefficient-major, colour channel fastest; `round(x * 128) + 128`, then snapped to buckets of
8 for degree 1 and 16 above, as the reference's default 5/4 bits). We write version 3, whose
rotation is "smallest three": 2 bits for the index of the largest component (of xyzw), then
for each other component in xyzw order a sign bit and 9 bits of `|q_i| / sqrt(1/2)`, packed
into a little-endian uint32 with the first component in the highest bits; the largest
component is made positive. The reader also takes version 2 (xyz bytes `q * 127.5 + 127.5`
of a w >= 0 quaternion).

SPZ stores RUB axes (x right, y up, z back). Our world frame is treated as RDF (OpenCV's, as
3DGS PLYs are), so positions, quaternions and SH coefficients are mirrored in y and z on write
and back on read, as the reference does for `PackOptions.from = RDF`.
"""

from __future__ import annotations

import gzip
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mvgeo.common.atomic import atomic_write_bytes
from mvgeo.common.errors import InputError
from splat.gaussian_model import GaussianModel

__all__ = ["EXPORT_FORMATS", "SH_C0", "SPLAT_BYTES_PER_GAUSSIAN", "SPZ_MAGIC", "SpzHeader", "export_model",
           "read_splat", "read_spz", "read_spz_header", "splat_bytes", "splat_importance_order", "spz_bytes",
           "write_splat", "write_spz"]

#: Zeroth-order real SH basis constant, `1 / (2 sqrt(pi))`.
SH_C0 = 0.28209479177387814
SPLAT_BYTES_PER_GAUSSIAN = 32
SPZ_MAGIC = 0x5053474E
SPZ_VERSION = 3
#: The reference's default fixed-point precision (about 0.24 mm when units are metres).
SPZ_FRACTIONAL_BITS = 12
#: DC colour scale of spz (smaller than SH_C0 so colours slightly out of [0, 1] survive).
SPZ_COLOR_SCALE = 0.15
_SPZ_FLAG_ANTIALIASED = 0x1
_SPZ_FLAG_EXTENSIONS = 0x2
_SPZ_HEADER = struct.Struct("<IIIBBBB")
_SQRT1_2 = float(np.sqrt(0.5))
#: Formats `splat export` writes ("html" is `splat.viewer.export_html`).
EXPORT_FORMATS = ("ply", "splat", "spz", "html")

# Sign of each SH coefficient (3DGS order, degrees 1..3) under (x, y, z) -> (x, -y, -z): the basis
# function's parity in y and z. Degree 1: y, z, x; degree 2: xy, yz, 3z^2-1, xz, x^2-y^2; degree 3:
# y(3x^2-y^2), xyz, y(5z^2-1), z(5z^2-3), x(5z^2-1), z(x^2-y^2), x(x^2-3y^2).
_SH_FLIP_RDF_RUB = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)
_P_FLIP_RDF_RUB = np.array([1, -1, -1], np.float32)


def _numpy(model: GaussianModel) -> dict[str, np.ndarray]:
    with torch.no_grad():
        arrays = {name: getattr(model, name).detach().float().cpu().numpy()
                  for name in ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")}
    for name, a in arrays.items():
        if not np.isfinite(a).all():
            raise InputError(f"the model's {name} contain NaN or inf; it cannot be exported",
                             fix="re-train, or export an earlier checkpoint")
    return arrays


def _unit_quats(q: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if (norm <= 0).any():
        raise InputError("the model has a zero quaternion; it cannot be exported")
    return q / norm


def _model(means, quats, log_scales, opacity_logits, sh0, shN) -> GaussianModel:
    def t(a):
        return torch.as_tensor(np.ascontiguousarray(a, dtype=np.float32))

    return GaussianModel(t(means), t(quats), t(log_scales), t(opacity_logits), t(sh0), t(shN))


def _logit(p: np.ndarray) -> np.ndarray:
    # Bytes 0 and 255 are 0 and 1 exactly; keep the logit finite (a 1e-4 opacity is invisible).
    p = np.clip(p, 1e-4, 1.0 - 1e-4)
    return np.log(p / (1.0 - p))


# ----------------------------------------------------------------------------------------- .splat


def splat_importance_order(log_scales: np.ndarray, opacity_logits: np.ndarray) -> np.ndarray:
    """Indices by descending `exp(sum(log_scales)) * sigmoid(opacity)` (ties keep their order).

    Computed in log space, `sum(log_scales) + log(sigmoid(opacity))`, so huge scales do not
    overflow; the order is the same.
    """
    log_sig = -np.logaddexp(0.0, -np.asarray(opacity_logits, np.float64))
    score = np.asarray(log_scales, np.float64).sum(axis=1) + log_sig
    return np.argsort(-score, kind="stable")


def splat_bytes(model: GaussianModel) -> bytes:
    """The model as antimatter15 `.splat` bytes (exactly 32 x N)."""
    a = _numpy(model)
    n = len(a["means"])
    order = splat_importance_order(a["log_scales"], a["opacity_logits"])
    rgb = 0.5 + SH_C0 * a["sh0"][:, 0, :]
    alpha = 1.0 / (1.0 + np.exp(-a["opacity_logits"].astype(np.float64)))
    rgba = np.concatenate([rgb, alpha[:, None]], axis=1)
    rot = np.clip(np.rint(_unit_quats(a["quats"].astype(np.float64)) * 128.0 + 128.0), 0, 255)
    rec = np.empty(n, dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    rec["pos"] = a["means"]
    scale = np.exp(a["log_scales"].astype(np.float64))
    if not (scale <= np.finfo(np.float32).max).all():
        raise InputError(f"the model has scales beyond float32's range (log scale up to "
                         f"{float(a['log_scales'].max()):.3g}); .splat stores them as float32",
                         fix="re-train (a scale that large is a diverged Gaussian), or export as .ply")
    rec["scale"] = scale
    rec["rgba"] = np.clip(np.rint(rgba * 255.0), 0, 255)
    rec["rot"] = rot
    out = rec[order].tobytes()
    assert len(out) == SPLAT_BYTES_PER_GAUSSIAN * n
    return out


def write_splat(path: str | Path, model: GaussianModel) -> None:
    """Write `model` as a `.splat` file (atomically)."""
    atomic_write_bytes(path, splat_bytes(model))


def read_splat(path: str | Path) -> GaussianModel:
    """Read a `.splat` file into an SH-degree-0 `GaussianModel`, in the file's (importance) order.

    Decoding: scale -> log, RGB byte -> f_dc = (byte / 255 - 0.5) / SH_C0, alpha byte -> logit
    (clipped to [1e-4, 1 - 1e-4]), rotation bytes -> (byte - 128) / 128 (not renormalised:
    the renderer normalises).

    Raises:
        InputError: missing file, or a size that is not a multiple of 32 bytes.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(".splat file not found", path=path)
    data = path.read_bytes()
    if len(data) % SPLAT_BYTES_PER_GAUSSIAN:
        raise InputError(f"{len(data)} bytes is not a multiple of {SPLAT_BYTES_PER_GAUSSIAN}: not a .splat file",
                         path=path)
    rec = np.frombuffer(data, dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    n = len(rec)
    scale = rec["scale"].astype(np.float64)
    if (scale <= 0).any() or not np.isfinite(rec["pos"]).all():
        raise InputError("the .splat file has non-positive scales or non-finite positions", path=path)
    rgba = rec["rgba"].astype(np.float64) / 255.0
    return _model(rec["pos"], (rec["rot"].astype(np.float64) - 128.0) / 128.0, np.log(scale), _logit(rgba[:, 3]),
                  ((rgba[:, :3] - 0.5) / SH_C0)[:, None, :], np.zeros((n, 0, 3)))


# ------------------------------------------------------------------------------------------- .spz


@dataclass(frozen=True)
class SpzHeader:
    """The 16-byte header of an `.spz` stream (after gunzip)."""

    magic: int
    version: int
    num_points: int
    sh_degree: int
    fractional_bits: int
    flags: int
    reserved: int


def _spz_fractional_bits(means: np.ndarray, preferred: int) -> int:
    """The largest fractional bit count <= `preferred` whose 24-bit fixed point holds every coordinate."""
    limit = 2 ** 23 - 1
    peak = float(np.abs(means).max()) if means.size else 0.0
    for bits in range(preferred, -1, -1):
        if np.rint(peak * 2.0 ** bits) <= limit:  # as the positions are rounded (`spz_bytes`)
            return bits
    raise InputError(f"a Gaussian lies {peak:.3g} units from the origin; .spz positions are 24-bit fixed point "
                     f"(at most {limit} units)", fix="export as .ply or .splat")


def _pack_quats_smallest_three(q_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) unit xyzw -> (N, 4) uint8: the little-endian uint32 of spz version 3."""
    i_largest = np.argmax(np.abs(q_xyzw), axis=1)
    negate = q_xyzw[np.arange(len(q_xyzw)), i_largest] < 0
    comp = i_largest.astype(np.uint64)
    for i in range(4):
        keep = i_largest != i
        negbit = ((q_xyzw[:, i] < 0) ^ negate).astype(np.uint64)
        mag = np.floor(511.0 * np.abs(q_xyzw[:, i]) / _SQRT1_2 + 0.5).astype(np.uint64)
        comp = np.where(keep, (comp << np.uint64(10)) | (negbit << np.uint64(9)) | mag, comp)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def _unpack_quats_smallest_three(packed: np.ndarray) -> np.ndarray:
    """(N, 4) uint8 -> (N, 4) unit xyzw."""
    comp = packed.reshape(-1, 4).copy().view("<u4")[:, 0].astype(np.uint64)
    i_largest = (comp >> np.uint64(30)).astype(np.int64)
    q = np.zeros((len(comp), 4))
    for i in range(3, -1, -1):
        here = i_largest != i
        mag = (comp & np.uint64(511)).astype(np.float64)
        neg = ((comp >> np.uint64(9)) & np.uint64(1)).astype(bool)
        value = _SQRT1_2 * mag / 511.0
        q[:, i] = np.where(here, np.where(neg, -value, value), 0.0)
        comp = np.where(here, comp >> np.uint64(10), comp)
    rest = np.clip(1.0 - np.sum(q ** 2, axis=1), 0.0, None)
    q[np.arange(len(q)), i_largest] = np.sqrt(rest)
    return q


def _quantize_sh(x: np.ndarray, bucket: int) -> np.ndarray:
    q = np.rint(x.astype(np.float64) * 128.0) + 128.0
    q = np.floor((q + bucket // 2) / bucket) * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def spz_bytes(model: GaussianModel, *, fractional_bits: int = SPZ_FRACTIONAL_BITS) -> bytes:
    """The model as `.spz` (version 3) bytes: gzip of header + attribute arrays.

    `fractional_bits` is lowered automatically when a coordinate would not fit in 24 bits.

    Raises:
        InputError: non-finite parameters, or coordinates beyond the 24-bit range even with 0 bits.
    """
    if not 0 <= fractional_bits <= 23:
        raise InputError(f"fractional_bits must be in 0..23, got {fractional_bits}")
    a = _numpy(model)
    n = len(a["means"])
    degree = model.sh_degree_max
    bits = _spz_fractional_bits(a["means"].astype(np.float64), fractional_bits)
    means = a["means"].astype(np.float64) * _P_FLIP_RDF_RUB
    fixed = np.rint(means * 2.0 ** bits).astype(np.int64).reshape(-1)
    positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], axis=1).astype(np.uint8)
    alpha = 1.0 / (1.0 + np.exp(-a["opacity_logits"].astype(np.float64)))
    alphas = np.clip(np.rint(alpha * 255.0), 0, 255).astype(np.uint8)
    colors = np.clip(np.rint(a["sh0"][:, 0, :].astype(np.float64) * (SPZ_COLOR_SCALE * 255.0) + 127.5), 0, 255)
    scales = np.clip(np.rint((a["log_scales"].astype(np.float64) + 10.0) * 16.0), 0, 255).astype(np.uint8)
    q = _unit_quats(a["quats"].astype(np.float64))  # wxyz
    q_xyzw = np.concatenate([q[:, 1:] * _P_FLIP_RDF_RUB, q[:, :1]], axis=1)
    rotations = _pack_quats_smallest_three(q_xyzw)
    sh = a["shN"].astype(np.float64) * _SH_FLIP_RDF_RUB[: a["shN"].shape[1], None]  # (N, K-1, 3)
    sh_q = np.empty(sh.shape, np.uint8)
    if sh.shape[1]:
        sh_q[:, :3] = _quantize_sh(sh[:, :3], 8)
        sh_q[:, 3:] = _quantize_sh(sh[:, 3:], 16)
    header = _SPZ_HEADER.pack(SPZ_MAGIC, SPZ_VERSION, n, degree, bits, 0, 0)
    raw = b"".join([header, positions.tobytes(), alphas.tobytes(), colors.astype(np.uint8).tobytes(),
                    scales.tobytes(), rotations.tobytes(), sh_q.tobytes()])
    return gzip.compress(raw, compresslevel=6, mtime=0)


def write_spz(path: str | Path, model: GaussianModel, *, fractional_bits: int = SPZ_FRACTIONAL_BITS) -> None:
    """Write `model` as an `.spz` file (atomically)."""
    atomic_write_bytes(path, spz_bytes(model, fractional_bits=fractional_bits))


def _spz_payload(path: Path) -> bytes:
    if not path.is_file():
        raise InputError(".spz file not found", path=path)
    try:
        return gzip.decompress(path.read_bytes())
    except (OSError, EOFError) as exc:
        raise InputError(f"not a gzip stream ({exc}): not an .spz file", path=path) from exc


def _parse_header(raw: bytes, path: Path) -> SpzHeader:
    if len(raw) < _SPZ_HEADER.size:
        raise InputError("the .spz stream is shorter than its 16-byte header", path=path)
    header = SpzHeader(*_SPZ_HEADER.unpack_from(raw))
    if header.magic != SPZ_MAGIC:
        raise InputError(f"bad magic 0x{header.magic:08x} (expected 0x{SPZ_MAGIC:08x}, 'NGSP')", path=path)
    if header.version not in (2, 3):
        raise InputError(f".spz version {header.version} is not supported (2 and 3 are)", path=path)
    if header.sh_degree > 3:
        raise InputError(f"SH degree {header.sh_degree} is not supported (0..3)", path=path)
    if header.flags & _SPZ_FLAG_EXTENSIONS:
        raise InputError(".spz extensions are not supported", path=path, fix="re-save the file without extensions")
    return header


def read_spz_header(path: str | Path) -> SpzHeader:
    """The header of an `.spz` file.

    Raises:
        InputError: missing file, not gzip, bad magic or unsupported version/degree/flags.
    """
    path = Path(path)
    return _parse_header(_spz_payload(path), path)


def read_spz(path: str | Path) -> GaussianModel:
    """Read an `.spz` file (version 2 or 3, no extensions) into a `GaussianModel` (our RDF axes).

    Raises:
        InputError: see `read_spz_header`, or a payload shorter than the header says.
    """
    path = Path(path)
    raw = _spz_payload(path)
    h = _parse_header(raw, path)
    n, k_rest = h.num_points, (h.sh_degree + 1) ** 2 - 1
    rot_bytes = 4 if h.version >= 3 else 3
    sizes = {"positions": 9 * n, "alphas": n, "colors": 3 * n, "scales": 3 * n, "rotations": rot_bytes * n,
             "sh": 3 * k_rest * n}
    if len(raw) < _SPZ_HEADER.size + sum(sizes.values()):
        raise InputError(f"the .spz payload is {len(raw)} bytes, shorter than its header's {n} Gaussians need",
                         path=path)
    parts, offset = {}, _SPZ_HEADER.size
    for name, size in sizes.items():
        parts[name] = np.frombuffer(raw, np.uint8, size, offset)
        offset += size
    b = parts["positions"].reshape(-1, 3).astype(np.int64)
    fixed = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.reshape(n, 3) / 2.0 ** h.fractional_bits * _P_FLIP_RDF_RUB
    opacity = _logit(parts["alphas"].astype(np.float64) / 255.0)
    sh0 = ((parts["colors"].reshape(n, 3) / 255.0 - 0.5) / SPZ_COLOR_SCALE)[:, None, :]
    log_scales = parts["scales"].reshape(n, 3) / 16.0 - 10.0
    if h.version >= 3:
        q_xyzw = _unpack_quats_smallest_three(parts["rotations"].reshape(n, 4))
    else:
        xyz = parts["rotations"].reshape(n, 3) / 127.5 - 1.0
        q_xyzw = np.concatenate([xyz, np.sqrt(np.clip(1.0 - np.sum(xyz ** 2, axis=1), 0, None))[:, None]], axis=1)
    quats = np.concatenate([q_xyzw[:, 3:], q_xyzw[:, :3] * _P_FLIP_RDF_RUB], axis=1)
    shN = ((parts["sh"].reshape(n, k_rest, 3).astype(np.float64) - 128.0) / 128.0
           * _SH_FLIP_RDF_RUB[:k_rest, None])
    return _model(means, quats, log_scales, opacity, sh0, shN)


# ----------------------------------------------------------------------------------------- export


def export_model(model: GaussianModel, fmt: str, out: str | Path) -> Path:
    """Write `model` as `fmt` ("ply", "splat", "spz") to `out`; return the path.

    ("html" needs cameras and viser: `splat.viewer.export_html`.)

    Raises:
        InputError: unknown format.
    """
    from splat.ply import write_gaussian_ply

    out = Path(out)
    writers = {"ply": write_gaussian_ply, "splat": write_splat, "spz": write_spz}
    if fmt not in writers:
        raise InputError(f"unknown export format {fmt!r}", fix=f"choose one of {', '.join(writers)}")
    writers[fmt](out, model)
    return out
