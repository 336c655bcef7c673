"""The shared base is light: importing `mvgeo.common` or any of its modules loads no cv2, pycolmap
or torch and changes no environment variable; the heavy libraries come on first use."""

from __future__ import annotations

import json
import os
import pkgutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import mvgeo.common

HEAVY = ("cv2", "pycolmap", "torch")

#: Each import runs in a fresh interpreter, which reports what it loaded and which variables changed.
PROBE = textwrap.dedent("""
    import importlib, json, os, sys
    before = dict(os.environ)
    importlib.import_module(sys.argv[1])
    after = dict(os.environ)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    print(json.dumps({"heavy": [m for m in sys.argv[2:] if m in sys.modules], "env_changed": changed}))
""")


def _common_modules() -> list[str]:
    names = [mvgeo.common.__name__]
    names += [info.name for info in pkgutil.walk_packages(mvgeo.common.__path__, prefix="mvgeo.common.")]
    return sorted(names)


def _clean_env() -> dict[str, str]:
    """The environment without the thread variables, so that a module setting one (even with
    `setdefault`) shows as a change."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("OMP_", "MKL_", "OPENBLAS_"))}


def _probe(module: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", PROBE, module, *HEAVY], capture_output=True, text=True,
                          timeout=120, env=_clean_env())
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_the_module_list_is_complete():
    """Every file of mvgeo/common is probed (a new module is covered without editing this test)."""
    files = sorted(p.stem for p in Path(mvgeo.common.__path__[0]).glob("*.py") if p.stem != "__init__")
    assert [m.rpartition(".")[2] for m in _common_modules()[1:]] == files
    assert {"errors", "deps", "threads", "imageio"} <= set(files)


@pytest.mark.parametrize("module", _common_modules())
def test_importing_is_light_and_sets_no_environment(module):
    result = _probe(module)
    assert result["heavy"] == [], f"importing {module} loaded {result['heavy']}"
    assert result["env_changed"] == [], f"importing {module} changed {result['env_changed']}"


def test_the_probe_sees_heavy_imports_and_environment_changes():
    """The check can fail: `mvgeo.common.deps`' pycolmap is heavy once used, and a module that sets a
    variable is seen."""
    code = "import mvgeo.common.deps as d, os; d.pycolmap; os.environ['OMP_WAIT_POLICY'] = 'PASSIVE'"
    proc = subprocess.run([sys.executable, "-c", PROBE.replace("importlib.import_module(sys.argv[1])", code),
                           "unused", *HEAVY], capture_output=True, text=True, timeout=120, env=_clean_env())
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["heavy"] == ["cv2", "pycolmap"]
    assert "OMP_WAIT_POLICY" in result["env_changed"]


def test_deps_still_imports_cv2_before_pycolmap():
    code = ("import sys\nfrom mvgeo.common.deps import pycolmap\nnames = list(sys.modules)\n"
            "print(names.index('cv2') < names.index('pycolmap'))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "True"
