"""`mvgeo.common.imageio`: the name checks commands run before they write one output per input."""

import pytest


def test_check_distinct_stems_ignores_the_suffix_and_the_case(tmp_path):
    """Outputs are named `<stem>.png`: `a.png` and `a.jpg` would be one file, and so would `A.png` and
    `a.jpg` on a case-insensitive file system (macOS, Windows)."""
    from mvgeo.common.errors import InputError
    from mvgeo.common.imageio import check_distinct_stems

    check_distinct_stems(["a.png", "b.png", "ab.jpg"], path=tmp_path)
    for names in (["a.png", "a.jpg"], ["A.png", "b.png", "a.jpg"], ["x/v.png", "y/v.png"]):
        with pytest.raises(InputError, match="two images share the name") as err:
            check_distinct_stems(names, path=tmp_path)
        assert err.value.path == tmp_path and names[-1] in str(err.value)


def test_read_image_refuses_transparent_pixels_and_drops_an_opaque_alpha(tmp_path):
    """A photo's transparent pixels hold no colour of the scene (exporters often leave them black): read as
    RGB they would be denoised, aligned and splatted as a black patch, so such a file is refused by name. An
    alpha channel that is opaque everywhere (a screenshot, an export) is dropped as before."""
    import numpy as np

    from mvgeo.common.errors import InputError
    from mvgeo.common.imageio import read_image

    Image = pytest.importorskip("PIL.Image")
    rgb = np.zeros((24, 40, 3), np.uint8)
    rgb[..., 0] = np.linspace(0, 255, 40, dtype=np.uint8)[None, :]
    alpha = np.full((24, 40), 255, np.uint8)
    Image.fromarray(np.dstack([rgb, alpha])).save(tmp_path / "opaque.png")
    np.testing.assert_array_equal(read_image(tmp_path / "opaque.png"), rgb / np.float32(255))
    alpha[:, :5] = 0
    Image.fromarray(np.dstack([rgb, alpha])).save(tmp_path / "cut out.png")
    Image.fromarray(np.dstack([rgb[..., 0], alpha])).save(tmp_path / "gray alpha.png")  # LA
    pal = Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=64)
    pal.save(tmp_path / "palette.png", transparency=int(np.asarray(pal)[0, 0]))  # tRNS: one index transparent
    for name in ("cut out.png", "gray alpha.png", "palette.png"):
        with pytest.raises(InputError, match="transparent pixels") as err:
            read_image(tmp_path / name)
        assert err.value.path == tmp_path / name and "flatten" in err.value.fix


def test_list_images_warns_once_about_images_in_subfolders(tmp_path, caplog):
    """Only the images directly in the folder are used: images in a subfolder were left out without a word."""
    import logging

    import numpy as np

    from mvgeo.common.imageio import list_images, write_image

    img = np.zeros((8, 8, 3), np.float32)
    for name in ("a.png", "more/b.png", "more/c.JPG", ".hidden/d.png", "empty/notes.txt"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        write_image(tmp_path / name, img) if name.endswith(("png", "JPG")) else (tmp_path / name).write_text("x")
    with caplog.at_level(logging.WARNING, logger="mvgeo.common.imageio"):
        assert list_images(tmp_path) == [tmp_path / "a.png"]
        assert list_images(tmp_path) == [tmp_path / "a.png"]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "2 image(s)" in warnings[0] and "more/ (2)" in warnings[0], warnings
    assert ".hidden" not in warnings[0] and "empty" not in warnings[0]
