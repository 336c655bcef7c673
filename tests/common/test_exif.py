"""JPEG EXIF orientation: `read_image` returns the photo upright, for all eight orientations.

The fixtures are made here: PIL writes a JPEG with the EXIF Orientation tag (and the same pixels with
orientation 1); the reference is PIL's own `ImageOps.exif_transpose`.
"""

from __future__ import annotations

import numpy as np
import pytest

from mvgeo.common.imageio import apply_exif_orientation, jpeg_exif_orientation, read_image

Image = pytest.importorskip("PIL.Image")
ImageOps = pytest.importorskip("PIL.ImageOps")


def _asymmetric_rgb(h: int = 24, w: int = 40) -> np.ndarray:
    """An image with no symmetry: a red block top-left, a green bar along the bottom, a blue ramp."""
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 2] = np.linspace(0, 255, w, dtype=np.uint8)[None, :]
    img[:8, :12] = (255, 0, 0)
    img[-5:, :] = (0, 255, 0)
    return img


def _save_jpeg(path, pixels: np.ndarray, orientation: int) -> None:
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(pixels).save(path, quality=98, exif=exif.tobytes())


@pytest.mark.parametrize("orientation", range(1, 9))
def test_read_image_applies_exif_orientation(tmp_path, orientation):
    pixels = _asymmetric_rgb()
    _save_jpeg(tmp_path / "plain.jpg", pixels, 1)
    _save_jpeg(tmp_path / "tagged.jpg", pixels, orientation)
    assert jpeg_exif_orientation((tmp_path / "tagged.jpg").read_bytes()) == orientation
    got = read_image(tmp_path / "tagged.jpg")
    with Image.open(tmp_path / "tagged.jpg") as im:
        upright = np.asarray(ImageOps.exif_transpose(im).convert("RGB"), np.float32) / 255.0
    assert got.shape == upright.shape == ((24, 40, 3) if orientation <= 4 else (40, 24, 3))
    # Two JPEG decoders (cv2's, PIL's) may differ by a few levels; a wrong orientation moves whole blocks.
    assert np.mean(np.abs(got - upright)) < 2 / 255
    # Same decoder, same pixels: exactly our orientation of the untagged file.
    np.testing.assert_array_equal(got, apply_exif_orientation(read_image(tmp_path / "plain.jpg"), orientation))


def test_files_without_exif_are_read_as_stored(tmp_path):
    Image.fromarray(_asymmetric_rgb()).save(tmp_path / "a.jpg", quality=98)
    Image.fromarray(_asymmetric_rgb()).save(tmp_path / "a.png")
    assert jpeg_exif_orientation((tmp_path / "a.jpg").read_bytes()) == 1
    assert jpeg_exif_orientation((tmp_path / "a.png").read_bytes()) == 1
    assert read_image(tmp_path / "a.jpg").shape == (24, 40, 3)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), _asymmetric_rgb() / np.float32(255))


def test_corrupt_exif_block_reads_as_orientation_one():
    # SOI, APP1 "Exif" with a truncated TIFF header, then SOS
    data = b"\xff\xd8" + b"\xff\xe1\x00\x0a" + b"Exif\x00\x00II" + b"\xff\xda\x00\x02"
    assert jpeg_exif_orientation(data) == 1


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
def test_read_image_applies_a_webp_exif_orientation(tmp_path, orientation):
    """WebP carries EXIF in a RIFF chunk (`webp_exif_orientation`); lossless, so the pixels compare exactly."""
    from mvgeo.common.imageio import webp_exif_orientation

    pixels = _asymmetric_rgb()
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(pixels).save(tmp_path / "tagged.webp", lossless=True, exif=exif.tobytes())
    assert webp_exif_orientation((tmp_path / "tagged.webp").read_bytes()) == orientation
    with Image.open(tmp_path / "tagged.webp") as im:
        upright = np.asarray(ImageOps.exif_transpose(im).convert("RGB"), np.float32) / 255.0
    np.testing.assert_array_equal(read_image(tmp_path / "tagged.webp"), upright)
    Image.fromarray(pixels).save(tmp_path / "plain.webp", lossless=True)
    assert webp_exif_orientation((tmp_path / "plain.webp").read_bytes()) == 1
    assert webp_exif_orientation(b"RIFF\x10\x00\x00\x00WEBPEXIF\xff\xff\xff\x7fII") == 1  # truncated chunk
