"""The EXIF 35 mm-equivalent focal length (FocalLengthIn35mmFilm): read from JPEG and PNG headers, and the
one focal prior a set of photos gives (`mvgeo.align.intrinsics`). Fixtures are written here with Pillow."""

from __future__ import annotations

import numpy as np
import pytest

from mvgeo.align.intrinsics import FULL_FRAME_DIAGONAL_MM, FocalPrior, common_focal_prior, exif_focal_prior
from mvgeo.common.imageio import exif_focal_35mm

Image = pytest.importorskip("PIL.Image")

EXIF_IFD, FOCAL_35MM = 0x8769, 0xA405


def _save(path, focal_35mm=None, *, in_ifd0: bool = False, size_wh=(40, 30)):
    exif = Image.Exif()
    if focal_35mm is not None:
        if in_ifd0:
            exif[FOCAL_35MM] = focal_35mm
        else:
            exif.get_ifd(EXIF_IFD)[FOCAL_35MM] = focal_35mm
    pixels = np.full((size_wh[1], size_wh[0], 3), 128, np.uint8)
    Image.fromarray(pixels).save(path, exif=exif.tobytes(), **({"quality": 95} if path.suffix == ".jpg" else {}))
    return path


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_the_35mm_focal_is_read_from_the_exif_ifd(tmp_path, suffix):
    assert exif_focal_35mm(_save(tmp_path / f"a{suffix}", 26)) == 26.0


def test_the_35mm_focal_is_also_found_in_ifd0(tmp_path):
    assert exif_focal_35mm(_save(tmp_path / "a.jpg", 50, in_ifd0=True)) == 50.0


def test_photos_without_a_35mm_focal_give_none(tmp_path):
    assert exif_focal_35mm(_save(tmp_path / "none.jpg")) is None
    assert exif_focal_35mm(_save(tmp_path / "zero.jpg", 0)) is None  # 0: "unknown" in the standard
    (tmp_path / "junk.jpg").write_bytes(b"not an image")
    assert exif_focal_35mm(tmp_path / "junk.jpg") is None
    assert exif_focal_35mm(tmp_path / "missing.jpg") is None


def test_a_35mm_focal_in_pixels_keeps_the_diagonal_field_of_view():
    # A 36 x 24 mm frame imaged at 3600 x 2400 px: 100 px per mm, so a 50 mm lens is 5000 px.
    assert FocalPrior(50.0).focal_px((3600, 2400)) == pytest.approx(5000.0)
    # Any size with the same diagonal field of view: the half-diagonal angle atan(diag / 2f) is the frame's.
    for wh in [(4032, 3024), (640, 480), (1600, 1200), (256, 192)]:
        f = FocalPrior(26.0).focal_px(wh)
        assert np.arctan(np.hypot(*wh) / 2 / f) == pytest.approx(np.arctan(FULL_FRAME_DIAGONAL_MM / 2 / 26.0))
    # The rule of thumb f35 / 35 * max(W, H): 1.1 % under for 4:3, 2.8 % over for 3:2 (the module docstring)
    assert (26.0 / 35.0 * 4032) / FocalPrior(26.0).focal_px((4032, 3024)) == pytest.approx(0.989, abs=0.001)
    assert (26.0 / 35.0 * 3600) / FocalPrior(26.0).focal_px((3600, 2400)) == pytest.approx(1.028, abs=0.001)
    with pytest.raises(ValueError, match="positive"):
        FocalPrior(0.0)


def test_one_prior_only_when_every_photo_has_the_same_focal(tmp_path):
    same = [_save(tmp_path / f"s{k}.jpg", 28) for k in range(3)]
    prior, why = exif_focal_prior(same)
    assert prior == FocalPrior(28.0, "exif") and why == ""
    prior, why = exif_focal_prior(same + [_save(tmp_path / "zoomed.jpg", 52)])
    assert prior is None and "28-52 mm" in why
    prior, why = exif_focal_prior(same + [_save(tmp_path / "bare.jpg")])
    assert prior is None and why.startswith("1 of 4 photos") and "bare.jpg" in why
    prior, why = common_focal_prior([24.0, 24.1, 23.9], ["a", "b", "c"])  # rounding within 1 %
    assert prior is not None and prior.focal_35mm == 24.0
    assert common_focal_prior([], [])[0] is None


def test_the_prior_in_pixels_is_pycolmaps(tmp_path):
    """pycolmap's image reader turns the same tag into its prior focal (`Camera.has_prior_focal_length`)."""
    from mvgeo.common.deps import cv2  # noqa: F401  (cv2 before pycolmap: docs/conventions.md)

    pycolmap = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(0)
    folder = tmp_path / "photos"
    folder.mkdir()
    for k, (suffix, wh) in enumerate([(".jpg", (600, 400)), (".png", (480, 360))]):
        exif = Image.Exif()
        exif.get_ifd(EXIF_IFD)[FOCAL_35MM] = 35
        Image.fromarray(rng.integers(0, 256, (wh[1], wh[0], 3), dtype=np.uint8)).save(
            folder / f"{k}{suffix}", exif=exif.tobytes())
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, folder, camera_mode=pycolmap.CameraMode.PER_IMAGE, device=pycolmap.Device.cpu)
    with pycolmap.Database.open(db) as database:
        cams = {(c.width, c.height): c for c in database.read_all_cameras()}
    for wh, cam in cams.items():
        assert cam.has_prior_focal_length
        # COLMAP's diagonal is 43.27 mm, hypot(36, 24) = 43.2666 here: 8e-5 apart
        assert cam.params[0] == pytest.approx(FocalPrior(35.0).focal_px(wh), rel=1e-4)
    assert set(cams) == {(600, 400), (480, 360)}


def test_photos_too_large_for_pillows_guard_give_none(tmp_path, monkeypatch):
    """Pillow refuses to open images above `MAX_IMAGE_PIXELS` (about 179 MP by default, e.g. 200 MP phone
    photos), and warns above half of it; the EXIF read gives no prior then, as without EXIF, and no warning."""
    import warnings

    path = _save(tmp_path / "big.jpg", 26, size_wh=(40, 30))
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 500)  # 1200 px: over twice the limit
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert exif_focal_35mm(path) is None
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # 1200 px: over the limit, under twice it
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert exif_focal_35mm(path) == 26.0


def _pillow_focal(path):
    """The focal as Pillow reads it after decoding the whole file (the reference of the PNG header scan)."""
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            value = exif.get_ifd(EXIF_IFD).get(FOCAL_35MM, exif.get(FOCAL_35MM))
    except Exception:
        return None
    return None if value is None or float(value) <= 0 else float(value)


def test_png_header_scan_agrees_with_pillow(tmp_path):
    from PIL import PngImagePlugin

    from mvgeo.common.imageio import _png_without_exif

    plain = tmp_path / "plain.png"
    Image.fromarray(np.full((30, 40, 3), 90, np.uint8)).save(plain)
    with_exif = _save(tmp_path / "exif.png", 35)
    info = PngImagePlugin.PngInfo()  # EXIF in a text chunk, as ImageMagick writes it
    raw = Image.Exif()
    raw.get_ifd(EXIF_IFD)[FOCAL_35MM] = 28
    hexed = raw.tobytes().hex()
    info.add_text("Raw profile type exif", f"\nexif\n{len(raw.tobytes())}\n{hexed}\n")
    text = tmp_path / "text.png"
    Image.fromarray(np.full((30, 40, 3), 90, np.uint8)).save(text, pnginfo=info)
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(plain.read_bytes()[:40])
    cases = {plain: True, with_exif: False, text: False, truncated: False}
    for path, scan in cases.items():
        assert _png_without_exif(path) is scan, path.name
        assert exif_focal_35mm(path) == _pillow_focal(path), path.name
    assert exif_focal_35mm(with_exif) == 35.0 and exif_focal_35mm(plain) is None
    assert _png_without_exif(_save(tmp_path / "a.jpg", 26)) is False  # not a PNG: Pillow decides
