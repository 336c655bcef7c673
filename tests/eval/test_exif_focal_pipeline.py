"""`denoise-gs run` keeps the input photos' EXIF focal: the working PNGs do not carry it, so the inputs stage
records it in sizes.json and every align stage starts its pairs there (`mvgeo.align.intrinsics`)."""

import json

import numpy as np
import pytest

import mvgeo.align
from eval.pipeline.align_stage import align
from eval.pipeline.inputs import SIZES_FILE, prepare_inputs, working_focal_prior
from eval.pipeline.stage import StageContext
from eval.pipeline.stage_settings import AlignStageSettings, InputsStageSettings
from mvgeo.align import AlignConfig
from mvgeo.align.intrinsics import FocalPrior
from mvgeo.common.errors import DisconnectedViewsError, InputError

Image = pytest.importorskip("PIL.Image")


def _photos(folder, focal_35mm, size_wh=(64, 48)):
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k, f35 in enumerate(focal_35mm):
        exif = Image.Exif()
        if f35 is not None:
            exif.get_ifd(0x8769)[0xA405] = f35
        pixels = rng.integers(0, 256, (size_wh[1], size_wh[0], 3), dtype=np.uint8)
        Image.fromarray(pixels).save(folder / f"{k:03d}.jpg", quality=95, exif=exif.tobytes())
    return folder


def _prepare(tmp_path, photos, max_size=32):
    ctx = StageContext("inputs", tmp_path / "out", {"noisy": photos}, InputsStageSettings(max_size, "x"), 0)
    prepare_inputs(ctx)
    return tmp_path / "out" / "inputs"


def test_the_inputs_stage_records_each_photos_exif_focal(tmp_path):
    working = _prepare(tmp_path, _photos(tmp_path / "photos", [26, 26, None]))
    sizes = json.loads((working / SIZES_FILE).read_text())
    assert [sizes[s]["focal_35mm"] for s in ("000", "001", "002")] == [26.0, 26.0, None]
    assert sizes["000"]["working"] == [32, 24]  # downscaled: the 35 mm-equivalent holds at any size
    prior, why = working_focal_prior(working)
    assert prior is None and "1 of 3" in why


def test_the_align_stage_starts_at_the_photos_exif_focal(tmp_path, monkeypatch):
    working = _prepare(tmp_path, _photos(tmp_path / "photos", [26, 26]))
    assert working_focal_prior(working) == (FocalPrior(26.0, "exif"), "")
    denoised = tmp_path / "denoised"
    denoised.mkdir()
    for name in ("000.png", "001.png"):
        (denoised / name).write_bytes(b"")
    calls = []

    class Stop(Exception):
        """Ends the stage once the fake aligner has recorded its call (no result needs building)."""

    def record(files, cfg, names=None, **kw):
        calls.append(kw)
        raise Stop

    monkeypatch.setattr(mvgeo.align, "align_images", record)
    inputs = {"images": denoised, "working": working}
    with pytest.raises(Stop):
        align(StageContext("align", tmp_path / "w1", inputs, AlignStageSettings(AlignConfig()), 0))
    with pytest.raises(Stop):  # switched off: no prior passed
        align(StageContext("align", tmp_path / "w2", inputs, AlignStageSettings(AlignConfig(exif_focal=False)), 0))
    assert calls == [{"focal_prior": FocalPrior(26.0, "exif")}, {}]


def test_a_missing_sizes_file_is_named(tmp_path):
    with pytest.raises(InputError, match="working sizes"):
        working_focal_prior(tmp_path)


def test_noisy_first_aligns_with_the_prior_too(tmp_path, monkeypatch):
    working = _prepare(tmp_path, _photos(tmp_path / "photos", [35, 35]))
    denoised = tmp_path / "denoised"
    denoised.mkdir()
    for name in ("000.png", "001.png"):
        (denoised / name).write_bytes(b"")
    calls = []

    def refuse(files, cfg, names=None, cloud_images=None, **kw):
        calls.append((files[0].parent.name, kw))
        raise DisconnectedViewsError("disconnected", views=("001.png",))

    monkeypatch.setattr(mvgeo.align, "align_images", refuse)
    ctx = StageContext("align", tmp_path / "w", {"images": denoised, "noisy": working, "working": working},
                       AlignStageSettings(AlignConfig(), photos="noisy_first"), 0)
    with pytest.raises(DisconnectedViewsError):
        align(ctx)
    prior = {"focal_prior": FocalPrior(35.0, "exif")}
    assert calls == [("inputs", prior), ("denoised", prior)]  # the noisy photos, then the denoised ones


@pytest.mark.parametrize("bad", ["26", -1, 0, [26], True, float("nan")])
def test_a_malformed_focal_in_sizes_json_is_named(tmp_path, bad):
    working = _prepare(tmp_path, _photos(tmp_path / "photos", [26, 26]))
    sizes = json.loads((working / SIZES_FILE).read_text())
    sizes["001"]["focal_35mm"] = bad
    (working / SIZES_FILE).write_text(json.dumps(sizes))
    with pytest.raises(InputError, match="focal_35mm") as info:
        working_focal_prior(working)
    assert info.value.path == working / SIZES_FILE and "--force" in info.value.fix
