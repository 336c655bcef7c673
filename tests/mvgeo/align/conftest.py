"""Fixtures shared by the alignment tests: one small rendered scene, and the PREVIEW alignment of it."""

import dataclasses
from pathlib import Path

import pytest

from mvgeo.align.api import PREVIEW, AlignResult, align_images
from mvgeo.common.imageio import list_images


@pytest.fixture(scope="session")
def llff6(tmp_path_factory) -> Path:
    """llff_like, 6 noisy views at 256x192 (read-only for the tests: copy before changing it)."""
    from data_synth import render_scene

    return render_scene("llff_like", tmp_path_factory.mktemp("llff6") / "llff", views=6, size_wh=(256, 192))


@pytest.fixture(scope="session")
def llff6_preview(llff6) -> AlignResult:
    """`align_images` of `llff6` with the PREVIEW preset, seed 0 (the defaults' candidate policy)."""
    return align_images(list_images(llff6 / "images"), dataclasses.replace(PREVIEW, seed=0))
