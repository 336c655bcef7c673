"""The Ray workers run the driver's code (`eval.distributed`, module docstring "Code"): the folders the
driver imports the project from come first on the workers' path, the setup hook keeps them first
whatever Ray puts in front later, and a task with other code than the driver's is refused.

Why: without this, a driver started from one checkout with the project installed (editable) from another
ran `eval` and `mvgeo` in its workers from the installed copy and `denoise` and `splat` from the driver's
folder, so the Ray rows of `denoise-gs eval --workers 2` came from a mix of two checkouts."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import eval.distributed
from eval.distributed import (
    PROJECT_PACKAGES,
    ClusterSettings,
    _check_code,
    project_code,
    project_roots,
    ray_cluster,
    worker_env,
)
from mvgeo.common.errors import InputError

REPO = Path(__file__).resolve().parents[2]


def _driver_folder() -> str:
    """The folder this test process imports the project from (the repository, unresolved as imported)."""
    return os.path.dirname(os.path.dirname(os.path.abspath(eval.__file__)))


def _fake_checkout(folder: Path) -> Path:
    """A folder with a `denoise` package that is not the project's (another checkout, say)."""
    (folder / "denoise").mkdir(parents=True)
    (folder / "denoise" / "__init__.py").write_text("OTHER_CHECKOUT = True\n")
    return folder


def _python(code: str, cwd: Path, timeout: float) -> str:
    """stdout of `python -c code` in `cwd`, with only the repository on PYTHONPATH."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_WAIT_POLICY": "PASSIVE", "DGS_NO_PROGRESS": "1"}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=cwd, env=env, capture_output=True,
                         text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_worker_env_puts_the_drivers_project_folder_first(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(["/elsewhere", _driver_folder()]))
    assert project_roots() == [_driver_folder()]  # every package of this repository, from one folder
    env = worker_env()
    assert env["PYTHONPATH"].split(os.pathsep) == [_driver_folder(), "/elsewhere"]  # the driver's first, once
    assert env["DGS_NO_PROGRESS"] == "1" and env["OMP_WAIT_POLICY"]


def test_ray_cluster_hands_the_workers_the_drivers_folder(monkeypatch):
    """What `ray.init` receives (no cluster is started): the environment and a hook with the folders."""
    import ray

    seen: dict = {}

    @contextlib.contextmanager
    def connected(ray_module, kwargs, settings, temp_dir, preload, tasks):
        seen.update(kwargs, preload=preload, tasks=tasks)
        if temp_dir is not None:
            os.rmdir(temp_dir)
        yield None

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(eval.distributed, "_connected", connected)
    with ray_cluster(ClusterSettings(workers=2), preload=("eval.evaluate",), tasks=3):
        env = seen["runtime_env"]["env_vars"]
        hook = seen["runtime_env"]["worker_process_setup_hook"]
    assert env["PYTHONPATH"].split(os.pathsep)[0] == _driver_folder()
    assert [_driver_folder()] in [cell.cell_contents for cell in hook.__closure__]  # the roots it installs
    assert (seen["preload"], seen["tasks"]) == (("eval.evaluate",), 3)  # the workers to start, handed on


def test_the_setup_keeps_the_drivers_packages_ahead_of_a_checkout_put_first_on_the_path(tmp_path):
    """Ray puts the driver's working folder in front of a worker's path after the setup hook: a checkout
    there must not shadow the driver's packages (here: `denoise` in a folder put first on `sys.path`)."""
    other = _fake_checkout(tmp_path / "other")

    def denoise_file(setup: bool) -> str:
        return _python(f"""
            import sys
            sys.path.insert(0, {str(other)!r})
            from eval.distributed import _import_project_from
            if {setup}:
                _import_project_from([{_driver_folder()!r}])
            import denoise
            print(denoise.__file__)
            """, tmp_path, 60).strip()

    # The fake checkout shadows the project without the setup (the test's premise), and not with it.
    assert denoise_file(False) == str(other / "denoise" / "__init__.py")
    assert denoise_file(True) == os.path.join(_driver_folder(), "denoise", "__init__.py")


def test_a_task_refuses_to_run_other_code_than_the_drivers():
    code = project_code()
    assert set(code) == set(PROJECT_PACKAGES)
    _check_code(code)  # the same code: runs
    with pytest.raises(InputError, match=r"other code than the driver: denoise from "):
        _check_code({**code, "denoise": "0" * 64})


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ray_workers_import_the_drivers_checkout(tmp_path):
    """A real local cluster: the driver imports the project through a folder of links that is not the
    installed copy, and runs from a folder holding another `denoise`; every task imports all of the
    project from the driver's folder."""
    shadow = tmp_path / "shadow"
    shadow.mkdir()
    for name in PROJECT_PACKAGES:
        (shadow / name).symlink_to(REPO / name, target_is_directory=True)
    other = _fake_checkout(tmp_path / "other")
    code = f"""
        import sys
        sys.path.insert(0, {str(shadow)!r})
        from eval.distributed import ClusterSettings, ray_cluster
        from tests.eval.test_distributed_code import imported_from
        with ray_cluster(ClusterSettings(workers=2)) as ex:
            for row in ex.run(imported_from, [0, 1]):
                print(row)
        """
    out = _python(code, other, 240).splitlines()
    expected = str({name: str(shadow / name / "__init__.py") for name in ("denoise", "eval", "mvgeo", "splat")})
    assert out == [expected, expected]


def imported_from(_: int) -> dict[str, str]:
    """In a task: the files the project's packages come from (imported now where not yet)."""
    import importlib

    for name in ("denoise", "eval.evaluate", "mvgeo.align", "splat"):
        importlib.import_module(name)
    return {name: sys.modules[name].__file__ for name in ("denoise", "eval", "mvgeo", "splat")}
