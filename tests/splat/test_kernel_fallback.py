"""The C++ kernels' loader: one warning per process when they are unavailable, the torch path then,
the ABI version and signature check of the compiled library, and the constants it receives.

Tests that change the loader get a fresh loader state and a private kernel cache (`fresh_loader`,
`DGS_SPLAT_BUILD_DIR`), so nothing leaks into the other tests or the user's cache; tests that only
read the library use the process's loaded kernels (`cpp_kernel`).
"""

from __future__ import annotations

import ctypes
import logging
import subprocess
import sys
import textwrap

import pytest
import torch

from splat import _cpu_kernel
from splat.composite import ALPHA_MAX, TRANSMITTANCE_MIN, composite_tiles
from splat.projection import ALPHA_MIN
from splat.rasterize import RasterConfig, rasterize
from splat.sh import eval_sh, eval_sh_fast
from splat.tiles import bin_gaussians


@pytest.fixture
def fresh_loader(monkeypatch, tmp_path):
    """Loader state as in a new process, with an empty kernel cache under tmp_path."""
    monkeypatch.setattr(_cpu_kernel, "_lib", None)
    monkeypatch.setattr(_cpu_kernel, "_error", None)
    monkeypatch.setattr(_cpu_kernel, "_warned", False)
    monkeypatch.setenv("DGS_SPLAT_BUILD_DIR", str(tmp_path / "kernels"))
    return tmp_path / "kernels"


@pytest.fixture
def no_compiler(fresh_loader, monkeypatch):
    monkeypatch.setenv("CXX", "/nonexistent")
    return fresh_loader


def _scene(dtype=torch.float64):
    g = torch.Generator().manual_seed(3)
    n = 12
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.3 + torch.tensor([0.0, 0.0, 2.0], dtype=dtype)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=dtype), dim=-1)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.05
    opac = torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    cam = torch.eye(4, dtype=dtype)[:3]
    K = torch.tensor([[20.0, 0, 12.0], [0, 20.0, 9.0], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, opac, colors, cam, K


def _render(backend):
    return rasterize(*_scene(), 24, 18, config=RasterConfig(backend=backend)).rgb


def test_without_compiler_auto_uses_torch_and_warns_once(no_compiler, caplog):
    caplog.set_level(logging.WARNING, logger="splat._cpu_kernel")
    first = _render("auto")
    for _ in range(3):
        again = _render("auto")
    warnings = [r for r in caplog.records if r.name == "splat._cpu_kernel" and r.levelno == logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert "no C++ compiler" in warnings[0].getMessage() and "/nonexistent" in warnings[0].getMessage()
    assert torch.equal(first, again)
    assert torch.equal(first, _render("torch"))  # the fallback is the torch path itself
    assert not any(no_compiler.rglob("*.so"))


def test_without_compiler_explicit_cpp_raises_and_sh_falls_back(no_compiler):
    with pytest.raises(_cpu_kernel.KernelBuildError, match="no C\\+\\+ compiler"):
        _render("cpp")
    assert "no C++ compiler" in _cpu_kernel.unavailable_reason()
    g = torch.Generator().manual_seed(0)
    sh, dirs = torch.randn(7, 16, 3, generator=g), torch.randn(7, 3, generator=g)
    assert torch.equal(eval_sh_fast(3, sh, dirs), eval_sh(3, sh, dirs))


@pytest.mark.slow
def test_warned_once_in_a_fresh_process(tmp_path):
    """The same in a real process: many renders without a compiler, exactly one warning on stderr."""
    code = textwrap.dedent("""
        import logging, torch
        from splat.rasterize import RasterConfig, rasterize
        logging.basicConfig(level=logging.WARNING)
        means = torch.tensor([[0.0, 0.0, 2.0]]); quats = torch.tensor([[1.0, 0, 0, 0]])
        scales = torch.full((1, 3), 0.2); opac = torch.tensor([0.8]); colors = torch.tensor([[0.9, 0.2, 0.1]])
        K = torch.tensor([[20.0, 0, 8.0], [0, 20.0, 6.0], [0, 0, 1]])
        for _ in range(20):
            out = rasterize(means, quats, scales, opac, colors, torch.eye(4)[:3], K, 16, 12)
        print(float(out.alpha.max()))
    """)
    env = {**__import__("os").environ, "CXX": "/nonexistent", "DGS_SPLAT_BUILD_DIR": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("C++ splat kernels unavailable") == 1, proc.stderr
    assert float(proc.stdout.split()[-1]) > 0.5


def test_library_reports_the_abi_version_and_signatures_of_this_module(cpp_kernel):
    lib = _cpu_kernel.load()
    assert lib.splat_kernel_abi_version() == _cpu_kernel._ABI_VERSION
    table = _cpu_kernel.parse_signatures(lib.splat_kernel_signatures().decode("ascii"))
    assert table == _cpu_kernel._SIGNATURES
    # The argtypes follow the table: pointers as void*, i64 as int64, f64 as double, i32 as int32.
    fwd = lib.splat_composite_forward_f32
    assert fwd.argtypes[:5] == [ctypes.c_int64] * 5 and fwd.argtypes[5] is ctypes.c_void_p
    assert fwd.argtypes[-4:] == [ctypes.c_double] * 3 + [ctypes.c_int32]


def test_abi_version_mismatch_is_refused(cpp_kernel, monkeypatch):
    monkeypatch.setattr(_cpu_kernel, "_ABI_VERSION", _cpu_kernel._ABI_VERSION + 100)
    with pytest.raises(_cpu_kernel.KernelBuildError, match="ABI version"):
        _cpu_kernel.check_library(_cpu_kernel.load())


@pytest.mark.slow
def test_abi_version_mismatch_rebuilds_once_then_falls_back_with_one_warning(cpp_kernel, fresh_loader, monkeypatch,
                                                                             caplog):
    _cpu_kernel.load()  # a good library in the private cache, then a module expecting another ABI
    monkeypatch.setattr(_cpu_kernel, "_lib", None)
    monkeypatch.setattr(_cpu_kernel, "_ABI_VERSION", _cpu_kernel._ABI_VERSION + 100)
    caplog.set_level(logging.INFO, logger="splat._cpu_kernel")
    assert not _cpu_kernel.available()
    assert not _cpu_kernel.available()
    messages = [r.getMessage() for r in caplog.records if r.name == "splat._cpu_kernel"]
    assert sum("rebuilding" in m for m in messages) == 1  # the cached library was rebuilt once
    warnings = [r for r in caplog.records if r.name == "splat._cpu_kernel" and r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "ABI version" in warnings[0].getMessage()
    assert torch.equal(_render("auto"), _render("torch"))


def test_signature_mismatch_is_refused(cpp_kernel, monkeypatch):
    table = dict(_cpu_kernel._SIGNATURES)
    codes = list(table["splat_sh_forward_f32"])
    codes[2] = "i64"  # degree passed as int64 where the kernel takes int32
    table["splat_sh_forward_f32"] = tuple(codes)
    monkeypatch.setattr(_cpu_kernel, "_SIGNATURES", table)
    with pytest.raises(_cpu_kernel.KernelBuildError, match="splat_sh_forward_f32"):
        _cpu_kernel.check_library(_cpu_kernel.load())


def test_parse_signatures():
    assert _cpu_kernel.parse_signatures("f(i64,f32*);g();") == {"f": ("i64", "f32*"), "g": ()}


def _flat_stack(opacities, dtype=torch.float64, size=16):
    """Nearly flat Gaussians (alpha ~ opacity on every pixel) stacked front to back, binned on all tiles."""
    n = len(opacities)
    means2d = torch.full((n, 2), size / 2.0, dtype=dtype)
    conics = torch.tensor([[1e-9, 0.0, 1e-9]] * n, dtype=dtype)
    colors = torch.ones(n, 1, dtype=dtype)
    opac = torch.tensor(opacities, dtype=dtype)
    bins = bin_gaussians(means2d, torch.full((n, 2), 2.0 * size, dtype=dtype), torch.arange(1, n + 1, dtype=dtype),
                         torch.ones(n, dtype=torch.bool), size, size)
    return means2d, conics, colors, opac, bins, size, size


@pytest.mark.parametrize("backend", ["cpp", "torch"])
def test_both_paths_read_the_python_constants(backend, request, monkeypatch):
    """The rules live in Python only: changing `splat.composite`'s constants changes the C++ result too
    (a value compiled into the kernel would not follow)."""
    if backend == "cpp":
        request.getfixturevalue("cpp_kernel")
    import splat.composite as comp

    def peak(opacities):
        acc, _ = composite_tiles(*_flat_stack(opacities), backend=backend)
        return acc.max().item()

    assert peak([1.0]) == pytest.approx(ALPHA_MAX, abs=1e-6)
    assert peak([ALPHA_MIN * 0.99]) == 0.0  # below the 1/255 floor: skipped
    assert peak([0.6, 0.6]) == pytest.approx(0.6 + 0.4 * 0.6, abs=1e-6)
    monkeypatch.setattr(comp, "ALPHA_MAX", 0.5)
    assert peak([1.0]) == pytest.approx(0.5, abs=1e-6)
    monkeypatch.setattr(comp, "ALPHA_MIN", 0.1)
    assert peak([0.09]) == 0.0 and peak([0.11]) == pytest.approx(0.11, abs=1e-6)
    monkeypatch.setattr(comp, "TRANSMITTANCE_MIN", 0.5)
    assert peak([0.45, 0.3]) == pytest.approx(0.45, abs=1e-6)  # the second layer would take T to 0.385 <= 0.5
    assert TRANSMITTANCE_MIN < 0.5 and ALPHA_MIN < 0.09  # the defaults do not produce these results


def test_sh_constants_come_from_python(cpp_kernel, monkeypatch):
    """The SH kernel reads the basis constants of `splat.sh` (scaled here: the result scales with them). The
    torch path evaluates the constants directly; the kernel's agreement with it is tested elsewhere."""
    import splat.sh as sh_mod

    g = torch.Generator().manual_seed(1)
    sh, dirs = torch.randn(9, 16, 3, generator=g, dtype=torch.float64), torch.randn(9, 3, generator=g,
                                                                                   dtype=torch.float64)
    base = eval_sh_fast(3, sh, dirs)
    monkeypatch.setattr(sh_mod, "_BASIS_CONSTANTS", sh_mod._BASIS_CONSTANTS * 2.0)
    assert torch.allclose(eval_sh_fast(3, sh, dirs), 2.0 * base, rtol=1e-12, atol=1e-12)
