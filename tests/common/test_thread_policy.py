"""The OpenMP wait policy: every command line sets OMP_WAIT_POLICY=PASSIVE before torch loads (OpenMP
reads it once, at load; spinning idle threads made training several times slower on a loaded
machine: docs/benchmarks.md, "Threads"); a value the user set is kept; a library import sets nothing
(tests/common/test_import_light.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]

#: Prints OMP_WAIT_POLICY at the moment torch is first imported, wherever that happens, and ends the
#: process there (what follows is not needed, and loading torch would take seconds).
HOOK = textwrap.dedent("""
    import os, sys
    class Hook:
        def find_spec(self, name, path, target=None):
            if name == "torch":
                print("policy-at-torch-import:", os.environ.get("OMP_WAIT_POLICY"), flush=True)
                os._exit(0)
            return None
    sys.meta_path.insert(0, Hook())
""")


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    env.update(extra)
    return env


def _policy_seen(code: str, env: dict[str, str]) -> str:
    proc = subprocess.run([sys.executable, "-c", HOOK + textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=300, env=env, cwd=ROOT)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("policy-at-torch-import:")]
    assert lines, (proc.returncode, proc.stdout[-2000:], proc.stderr[-2000:])
    return lines[-1].split(":", 1)[1].strip()


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_console_script_sets_passive_before_torch(script):
    """What the installed console script does: import the entry point, run `main(["--help"])`, then torch."""
    module, _, func = SCRIPTS[script].partition(":")
    code = f"""
        from {module} import {func}
        try:
            {func}(["--help"])
        except SystemExit:
            pass
        import torch
    """
    assert _policy_seen(code, _env()) == "PASSIVE"


@pytest.mark.parametrize("script", ["denoise", "splat"])
def test_installed_console_script_process(script):
    """The generated script in the environment's bin folder, run as a process."""
    path = Path(sys.executable).parent / script
    if not path.exists():
        pytest.skip(f"{path} is not installed")
    code = f"""
        import runpy
        sys.argv = [{str(path)!r}, "--help"]
        try:
            runpy.run_path({str(path)!r}, run_name="__main__")
        except SystemExit:
            pass
        import torch
    """
    assert _policy_seen(code, _env()) == "PASSIVE"


def test_user_value_is_kept():
    module, _, _ = SCRIPTS["splat"].partition(":")
    assert _policy_seen(f"import {module}\nimport torch\n", _env(OMP_WAIT_POLICY="ACTIVE")) == "ACTIVE"


def test_library_import_sets_nothing():
    """Importing the packages (not a command line) leaves the variable unset when torch loads."""
    code = "import mvgeo, splat, denoise, eval, data_synth\nimport splat.rasterize\nimport torch\n"
    assert _policy_seen(code, _env()) == "None"


def test_apply_after_torch_warns_and_reports_it(monkeypatch, caplog):
    """Called once torch is loaded (a stand-in module here), the variable is set for child processes
    but the call says, and logs, that this process's runtime ignores it."""
    import types

    from mvgeo.common.threads import apply_thread_policy

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.setitem(sys.modules, "torch", types.ModuleType("torch"))
    assert apply_thread_policy() is False
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    assert "after torch loaded" in caplog.text


def test_apply_before_torch_is_in_force_and_keeps_a_user_value(monkeypatch):
    from mvgeo.common.threads import apply_thread_policy

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.delitem(sys.modules, "torch", raising=False)
    assert apply_thread_policy() is True
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert apply_thread_policy() is True
    assert os.environ["OMP_WAIT_POLICY"] == "ACTIVE"
