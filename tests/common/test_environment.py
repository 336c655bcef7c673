"""The environment the lockfile promises: every named dependency imports,
mrcal works without pyfltk, and its pixel convention is what docs/conventions.md says."""

import subprocess
import sys

import numpy as np


def test_all_packages_import():
    code = "import mvgeo, splat, denoise, eval, data_synth, mrcal, pycolmap, open3d, cv2, torch, scipy, skimage"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr


def test_single_cv2_distribution():
    """opencv-python-headless must not be installed next to the contrib build (both ship cv2)."""
    from importlib.metadata import PackageNotFoundError, distribution

    distribution("opencv-contrib-python-headless")
    for other in ("opencv-python-headless", "opencv-python"):
        try:
            distribution(other)
        except PackageNotFoundError:
            continue
        raise AssertionError(f"{other} is installed next to opencv-contrib-python-headless")


def test_mrcal_pinhole_pixel_convention(rng):
    """mrcal's pinhole projection is u = fx x/z + cx with the top-left pixel centre
    at 0; ours adds 0.5 (docs/conventions.md). Checked on random points."""
    import mrcal

    fx, fy, cx_mrcal, cy_mrcal = 500.0, 480.0, 319.5, 239.5
    p = rng.normal(size=(50, 3)) + np.array([0.0, 0.0, 5.0])
    uv_mrcal = mrcal.project(p, "LENSMODEL_PINHOLE", np.array([fx, fy, cx_mrcal, cy_mrcal]))
    uv_ours = np.stack([fx * p[:, 0] / p[:, 2] + cx_mrcal + 0.5, fy * p[:, 1] / p[:, 2] + cy_mrcal + 0.5], -1)
    # float64 arithmetic on values ~1e3: 1e-9 px leaves room for rounding only
    np.testing.assert_allclose(uv_mrcal + 0.5, uv_ours, atol=1e-9)


def test_torch_runs_on_cpu():
    import torch

    x = torch.randn(8, 8)
    assert torch.allclose(x @ torch.eye(8), x)
