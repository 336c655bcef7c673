"""Console entry points (`mvgeo.common.launch`): a Ctrl-C while a command's module loads ends with one
line and exit code 130, not a traceback; every console script goes through them."""

from __future__ import annotations

import importlib
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from mvgeo.common import launch

ROOT = Path(__file__).resolve().parents[2]


def test_every_console_script_goes_through_the_launcher():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == {"data-synth", "mvgeo", "splat", "denoise", "denoise-gs"}
    for name, target in scripts.items():
        module, func = target.split(":")
        assert module == "mvgeo.common.launch", f"{name} bypasses the launcher: {target}"
        assert callable(getattr(launch, func))


@pytest.mark.parametrize("func, module", [("denoise_gs", "eval.cli"), ("mvgeo", "mvgeo.cli"),
                                          ("splat", "splat.cli"), ("denoise", "denoise.cli"),
                                          ("data_synth", "data_synth.cli")])
def test_each_launcher_runs_its_modules_main(monkeypatch, func, module):
    calls = []
    monkeypatch.setattr(importlib.import_module(module), "main", lambda argv: calls.append((module, argv)) or 7)
    assert getattr(launch, func)(["--help"]) == 7
    assert calls == [(module, ["--help"])]


@pytest.mark.skipif(sys.platform == "win32", reason="SIGINT to a child process")
def test_ctrl_c_while_the_module_loads_exits_130_without_traceback(tmp_path):
    ready = tmp_path / "ready"
    (tmp_path / "slow_cli.py").write_text(
        "import pathlib, time\n"
        f"pathlib.Path({str(ready)!r}).write_text('1')\n"
        "time.sleep(60)\n"
        "def main():\n    return 0\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    code = "import sys; from mvgeo.common.launch import _launch; sys.exit(_launch('slow_cli', None))"
    # A shell without job control starts background commands with SIGINT ignored, and an ignored SIGINT
    # stays ignored across exec (Python then installs no handler): the child gets the default disposition,
    # as a command typed at a terminal has, however the test run itself was started.
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 30
        while not ready.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the module never started loading"
            time.sleep(0.02)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == launch.EXIT_INTERRUPTED
    assert err == "interrupted\n"
    assert "Traceback" not in out + err
