"""The standard 3DGS PLY file (what the 3DGS viewers, gsplat and SuperSplat read).

Vertex properties, all float32, pre-activation:
`x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3`,
`f_rest` channel-major (all R coefficients, then G, then B), `rot` wxyz.
Normals are written as zeros and ignored on read.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from mvgeo.common.atomic import atomic_write_bytes
from mvgeo.common.errors import InputError
from splat.gaussian_model import GaussianModel


def _columns(k_rest: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * k_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def write_gaussian_ply(path: str | Path, model: GaussianModel) -> None:
    """Write `model` as a binary little-endian 3DGS PLY (atomically)."""
    n = model.num_gaussians
    with torch.no_grad():
        k_rest = model.shN.shape[1]
        parts = [
            model.means.float().cpu().numpy(),
            np.zeros((n, 3), np.float32),
            model.sh0.float().cpu().numpy().reshape(n, 3),
            # (N, K-1, 3) -> channel-major (N, 3, K-1) -> (N, 3 (K-1))
            model.shN.float().cpu().numpy().transpose(0, 2, 1).reshape(n, 3 * k_rest),
            model.opacity_logits.float().cpu().numpy()[:, None],
            model.log_scales.float().cpu().numpy(),
            model.quats.float().cpu().numpy(),
        ]
    data = np.concatenate(parts, axis=1).astype(np.float32)
    names = _columns(k_rest)
    rec = np.empty(n, dtype=[(name, "f4") for name in names])
    for i, name in enumerate(names):
        rec[name] = data[:, i]
    buf = io.BytesIO()
    PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<").write(buf)
    atomic_write_bytes(path, buf.getvalue())


def read_gaussian_ply(path: str | Path, *, device: str | torch.device = "cpu") -> GaussianModel:
    """Read a 3DGS PLY into a float32 `GaussianModel`.

    Raises:
        InputError: missing/corrupt file, or properties that are not the 3DGS layout.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("Gaussian PLY file not found", path=path,
                         fix="pass the point_cloud.ply written by `splat train`")
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"]
    except Exception as exc:  # plyfile raises several types for corrupt files
        raise InputError(f"cannot read PLY ({exc})", path=path,
                         fix="give a 3DGS Gaussian PLY (e.g. a `splat train` output's point_cloud.ply)") from exc
    props = [p.name for p in vertex.properties]
    n_rest = sum(1 for p in props if p.startswith("f_rest_"))
    if n_rest % 3 != 0 or (n_rest // 3 + 1) not in (1, 4, 9, 16):
        raise InputError(f"{n_rest} f_rest_* properties is not 3 * ((degree + 1)^2 - 1)", path=path)
    required = _columns(n_rest // 3)
    missing = [name for name in required if name not in props and name not in ("nx", "ny", "nz")]
    if missing:
        raise InputError(f"not a 3DGS Gaussian PLY: missing properties {missing[:6]}", path=path,
                         fix="a point-cloud PLY (xyz + rgb) is an initialisation, pass it with --init")
    n = len(vertex.data)
    k_rest = n_rest // 3

    def col(*names):
        return np.stack([np.asarray(vertex[name], dtype=np.float32) for name in names], axis=1)

    def t(a):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32, device=device)

    rest = col(*[f"f_rest_{i}" for i in range(3 * k_rest)]) if k_rest else np.zeros((n, 0), np.float32)
    return GaussianModel(
        means=t(col("x", "y", "z")),
        quats=t(col("rot_0", "rot_1", "rot_2", "rot_3")),
        log_scales=t(col("scale_0", "scale_1", "scale_2")),
        opacity_logits=t(col("opacity")[:, 0]),
        sh0=t(col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :]),
        shN=t(rest.reshape(n, 3, k_rest).transpose(0, 2, 1)),
    )
