"""Build (once, cached) and call the C++ CPU kernels: the compositor in `csrc/composite.cpp`
and the spherical-harmonics colour in `csrc/sh.cpp`.

The kernels are plain C++17 without torch headers, compiled (into one library) with the system
`g++` (or `$CXX`) into `~/.cache/denoise-gs/splat/<hash>/` (override with
`DGS_SPLAT_BUILD_DIR`); the hash covers the source, the compiler version and
the flags, so a changed source or compiler rebuilds. No network is used. The
build writes to a temporary file and renames it, so concurrent first builds
(two test processes) are safe. If no compiler is available, `available()`
is False and the renderer falls back to the torch reference path.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import torch

_log = logging.getLogger(__name__)

_SOURCES = [Path(__file__).resolve().parent / "csrc" / name for name in ("composite.cpp", "sh.cpp")]
_FLAGS = ["-O3", "-std=c++17", "-fPIC", "-shared", "-pthread"]
_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_error: str | None = None

_i64 = ctypes.c_int64
_ptr = ctypes.c_void_p


class KernelBuildError(RuntimeError):
    """The C++ compositor could not be compiled or loaded."""


def _compiler() -> str | None:
    cxx = os.environ.get("CXX") or "g++"
    return shutil.which(cxx)


def _build_dir() -> Path:
    root = os.environ.get("DGS_SPLAT_BUILD_DIR")
    if root:
        return Path(root)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "denoise-gs" / "splat"


def _build() -> ctypes.CDLL:
    cxx = _compiler()
    if cxx is None:
        raise KernelBuildError("no C++ compiler found (install g++ or set CXX)")
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True, check=False).stdout
    digest = hashlib.sha256(b"".join(s.read_bytes() for s in _SOURCES) + version.encode()
                            + " ".join(_FLAGS).encode()).hexdigest()[:16]
    out_dir = _build_dir() / digest
    lib_path = out_dir / "libsplat_composite.so"
    if not lib_path.exists():
        out_dir.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out_dir)
        os.close(fd)
        cmd = [cxx, *_FLAGS, *map(str, _SOURCES), "-o", tmp]
        _log.info("building the C++ splat compositor: %s", " ".join(cmd))
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            Path(tmp).unlink(missing_ok=True)
            raise KernelBuildError(f"compiling {' '.join(map(str, _SOURCES))} failed:\n{proc.stderr[-4000:]}")
        os.replace(tmp, lib_path)
    lib = ctypes.CDLL(str(lib_path))
    for suffix in ("f32", "f64"):
        fwd = getattr(lib, f"splat_composite_forward_{suffix}")
        fwd.restype = None
        fwd.argtypes = [_i64] * 5 + [_ptr] * 6 + [_i64] + [_ptr] * 3 + [ctypes.c_int]
        bwd = getattr(lib, f"splat_composite_backward_{suffix}")
        bwd.restype = None
        bwd.argtypes = [_i64] * 5 + [_ptr] * 6 + [_i64] + [_ptr] * 5 + [ctypes.c_int]
        sh_fwd = getattr(lib, f"splat_sh_forward_{suffix}")
        sh_fwd.restype = None
        sh_fwd.argtypes = [_i64, _i64, ctypes.c_int] + [_ptr] * 3
        sh_bwd = getattr(lib, f"splat_sh_backward_{suffix}")
        sh_bwd.restype = None
        sh_bwd.argtypes = [_i64, _i64, ctypes.c_int] + [_ptr] * 5
    return lib


def load() -> ctypes.CDLL:
    """The loaded library, building it on first use.

    Raises:
        KernelBuildError: no compiler, or the build failed (message has the compiler output).
    """
    global _lib, _error
    with _lock:
        if _lib is not None:
            return _lib
        if _error is not None:
            raise KernelBuildError(_error)
        try:
            _lib = _build()
        except (KernelBuildError, OSError) as exc:
            _error = str(exc)
            raise KernelBuildError(_error) from exc
        return _lib


def available() -> bool:
    """True when the kernel is built (or can be built) and loaded."""
    try:
        load()
    except KernelBuildError as exc:
        _log.warning("C++ splat compositor unavailable, using the torch path: %s", exc)
        return False
    return True


def _p(t: torch.Tensor) -> int:
    return t.data_ptr()


def _suffix(dtype: torch.dtype) -> str:
    if dtype == torch.float32:
        return "f32"
    if dtype == torch.float64:
        return "f64"
    raise TypeError(f"the C++ compositor supports float32/float64, got {dtype}")


def _threads(num_threads: int | None) -> int:
    return max(1, int(num_threads)) if num_threads is not None else torch.get_num_threads()


def forward(bins, means2d, conics, colors, opacities, width: int, height: int, *, num_threads: int | None = None):
    """Run the forward kernel. All tensors contiguous, CPU, one float dtype.

    `num_threads`: worker threads (default `torch.get_num_threads()`); results do not depend on it.

    Returns:
        accum (H, W, C), transmittance (H, W), last (H, W) int32.
    """
    lib = load()
    C = colors.shape[1]
    accum = torch.empty(height, width, C, dtype=colors.dtype)
    trans = torch.empty(height, width, dtype=colors.dtype)
    last = torch.empty(height, width, dtype=torch.int32)
    fn = getattr(lib, f"splat_composite_forward_{_suffix(colors.dtype)}")
    fn(bins.tiles_x, bins.tiles_y, bins.tile_size, width, height, _p(bins.tile_offsets), _p(bins.gaussian_ids),
       _p(means2d), _p(conics), _p(colors), _p(opacities), C, _p(accum), _p(trans), _p(last),
       _threads(num_threads))
    return accum, trans, last


def backward(bins, means2d, conics, colors, opacities, width, height, trans, last, grad_accum, grad_trans, *,
             num_threads: int | None = None):
    """Per-intersection gradient rows (I, 6 + C): [d means2d (2), d conics (3), d opacity, d colors (C)]."""
    lib = load()
    C = colors.shape[1]
    g_rows = torch.zeros(bins.gaussian_ids.numel(), 6 + C, dtype=colors.dtype)
    fn = getattr(lib, f"splat_composite_backward_{_suffix(colors.dtype)}")
    fn(bins.tiles_x, bins.tiles_y, bins.tile_size, width, height, _p(bins.tile_offsets), _p(bins.gaussian_ids),
       _p(means2d), _p(conics), _p(colors), _p(opacities), C, _p(trans), _p(last), _p(grad_accum),
       _p(grad_trans), _p(g_rows), _threads(num_threads))
    return g_rows


def sh_forward(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """SH colour (before the +0.5 offset): sh (N, K, 3), dirs (N, 3), contiguous CPU, one float dtype -> (N, 3)."""
    lib = load()
    out = torch.empty(dirs.shape[0], 3, dtype=sh.dtype)
    getattr(lib, f"splat_sh_forward_{_suffix(sh.dtype)}")(dirs.shape[0], sh.shape[1], degree, _p(sh), _p(dirs),
                                                         _p(out))
    return out


def sh_backward(degree: int, sh: torch.Tensor, dirs: torch.Tensor, grad_out: torch.Tensor):
    """Gradients (N, K, 3) of `sh` (zero for bases above `degree`) and (N, 3) of `dirs`."""
    lib = load()
    g_sh = torch.empty_like(sh)
    g_dirs = torch.empty_like(dirs)
    getattr(lib, f"splat_sh_backward_{_suffix(sh.dtype)}")(dirs.shape[0], sh.shape[1], degree, _p(sh), _p(dirs),
                                                          _p(grad_out), _p(g_sh), _p(g_dirs))
    return g_sh, g_dirs
