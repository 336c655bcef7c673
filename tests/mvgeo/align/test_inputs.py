"""The alignment's input stage (`mvgeo.align.inputs.load_inputs`): files read in parallel, in order."""

import cv2
import numpy as np
import pytest

from mvgeo.align.inputs import load_inputs
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image


def _write(path, rng, hw=(24, 32)):
    cv2.imwrite(str(path), rng.integers(0, 256, (*hw, 3), dtype=np.uint8))
    return path


def test_files_are_read_in_order_and_equal_to_read_image(tmp_path, rng):
    paths = [_write(tmp_path / f"{k:02d}.png", rng) for k in range(5)]
    inputs = load_inputs(paths, names=None, intrinsics=None, max_size_px=640)
    assert inputs.names == [p.name for p in paths]
    for p, a in zip(paths, inputs.images, strict=True):
        assert np.array_equal(a, read_image(p))


def test_the_first_unreadable_file_in_order_is_named(tmp_path, rng):
    """Two corrupt files among good ones: the error names the first in the given order, as a serial
    loop would, whichever thread fails first."""
    paths = [_write(tmp_path / f"{k:02d}.png", rng) for k in range(6)]
    for k in (2, 4):
        paths[k].write_bytes(b"not an image")
    with pytest.raises(InputError, match="02.png"):
        load_inputs(paths, names=None, intrinsics=None, max_size_px=640)
    with pytest.raises(InputError, match="04.png"):
        load_inputs(paths[3:], names=None, intrinsics=None, max_size_px=640)
