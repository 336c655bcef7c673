"""Regression test: importing pycolmap before cv2, then writing a PNG with cv2,
aborted the process (double free). `mvgeo.common.deps` fixes the order."""

import subprocess
import sys
import textwrap

import pytest

WRITE_PNG = "import numpy as np; cv2.imwrite(r'{path}', np.zeros((8, 8, 3), np.uint8)); print('wrote')"


def _run(code: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=timeout)


def test_safe_import_order_writes_png(tmp_path):
    out = tmp_path / "a.png"
    proc = _run("from mvgeo.common.deps import pycolmap, cv2\n" + WRITE_PNG.format(path=out))
    assert proc.returncode == 0, proc.stderr
    assert out.stat().st_size > 0


def test_every_package_import_then_png(tmp_path):
    """Importing all our packages (which may pull pycolmap) keeps cv2 safe."""
    out = tmp_path / "b.png"
    proc = _run("import mvgeo, splat, denoise, eval, data_synth\nimport cv2\n" + WRITE_PNG.format(path=out))
    assert proc.returncode == 0, proc.stderr
    assert out.exists()


def test_unsafe_order_is_still_dangerous(tmp_path):
    """Documents why the rule exists. If a future pycolmap/cv2 pair no longer
    crashes, this test says so (xfail), and the rule can be revisited."""
    out = tmp_path / "c.png"
    try:
        # a clean run takes < 2 s; the abort handler of the crash can hang instead of exiting
        crashed = _run("import pycolmap\nimport cv2\n" + WRITE_PNG.format(path=out), timeout=20).returncode != 0
    except subprocess.TimeoutExpired:
        crashed = True
    if not crashed:
        pytest.xfail("pycolmap-before-cv2 no longer crashes with the locked versions")
    assert crashed
