"""An alignment refusal inside the pipeline: the same error type, views and message as `mvgeo align`'s, with a
fix `denoise-gs run` can follow (it has no --allow-partial / --intrinsics / --ba; it registers every photo or
stops)."""

import pytest

import mvgeo.align
from eval.pipeline.align_stage import align, as_pipeline_refusal
from eval.pipeline.stage import StageContext
from eval.pipeline.stage_settings import AlignStageSettings
from mvgeo.align import AlignConfig
from mvgeo.common.errors import AlignmentRefusedError, DegenerateGeometryError, DisconnectedViewsError

MVGEO_FIX = "add views between the existing ones, or pass --allow-partial to register the others"
MESSAGE = "the reconstruction contradicts every verified image pair that links 1 of 12 views to the others"


def _refused(kind: str, views=("000007.png",)):
    return AlignmentRefusedError(MESSAGE, kind=kind, views=views, fix=MVGEO_FIX)


@pytest.mark.parametrize("kind", ["views_unsupported", "positions_undetermined"])
def test_views_to_leave_out_are_named_by_their_stems(kind):
    out = as_pipeline_refusal(_refused(kind, ("000007.png", "000003.png")))
    assert isinstance(out, AlignmentRefusedError) and isinstance(out, DegenerateGeometryError)
    assert (out.kind, out.views, out.message) == (kind, ("000007.png", "000003.png"), MESSAGE)
    assert out.fix.startswith("leave the photos ['000003', '000007'] out of the input folder")
    assert "pass --allow-partial" not in str(out) and "mvgeo align --allow-partial" in out.fix


def test_whole_reconstruction_reasons_get_the_pipeline_options():
    assert "--allow-focal-prior" in as_pipeline_refusal(_refused("focal_undetermined", ())).fix
    contradicted = as_pipeline_refusal(_refused("pairs_contradicted", ("a.png", "b.png")))
    assert contradicted.fix.startswith("add photos between the existing ones")
    assert "--intrinsics" not in str(contradicted) and "--allow-partial" not in str(contradicted)


def test_disconnected_views_keep_their_type_and_path():
    exc = DisconnectedViewsError("the pair graph is disconnected: images ['v3.png'] could not be related",
                                 views=("v3.png",), path="photos", fix="... or pass --allow-partial")
    out = as_pipeline_refusal(exc)
    assert type(out) is DisconnectedViewsError and out.views == ("v3.png",) and str(out.path) == "photos"
    assert out.message == exc.message and out.fix.startswith("leave the photos ['v3'] out of the input folder")
    unnamed = DisconnectedViewsError("no two images could be related", fix="check the images")
    assert as_pipeline_refusal(unnamed).fix == "check the images"


def test_other_geometry_errors_pass_unchanged():
    exc = DegenerateGeometryError("the alignment failed numerically")
    assert as_pipeline_refusal(exc) is exc


def test_the_round1_align_stage_raises_the_pipeline_refusal(tmp_path, monkeypatch):
    (tmp_path / "images").mkdir()
    for name in ("000003.png", "000007.png"):
        (tmp_path / "images" / name).write_bytes(b"")

    def refuse(files, cfg):
        raise _refused("views_unsupported")

    monkeypatch.setattr(mvgeo.align, "align_images", refuse)
    ctx = StageContext("align", tmp_path / "work", {"images": tmp_path / "images"},
                       AlignStageSettings(AlignConfig()), 0)
    with pytest.raises(AlignmentRefusedError) as info:
        align(ctx)
    assert info.value.views == ("000007.png",) and info.value.fix.startswith("leave the photos ['000007']")
    assert isinstance(info.value.__cause__, AlignmentRefusedError)  # mvgeo's own, chained


class _Stop(Exception):
    """Ends the stage once the fake aligner has recorded its call (no result needs building)."""


def _views(folder, names):
    folder.mkdir()
    for name in names:
        (folder / name).write_bytes(folder.name.encode())  # placeholders that differ between the folders
    return folder


def test_noisy_first_aligns_the_noisy_photos_under_the_denoised_names(tmp_path, monkeypatch):
    denoised = _views(tmp_path / "denoised", ("000003.png", "000007.png"))
    noisy = _views(tmp_path / "noisy", ("000003.jpg", "000007.jpg"))  # the working photos may differ in type
    calls = []

    def record(files, cfg, names=None, cloud_images=None):
        calls.append(([f.name for f in files], names, [(f.parent.name, f.name) for f in cloud_images]))
        raise _Stop

    monkeypatch.setattr(mvgeo.align, "align_images", record)
    ctx = StageContext("align", tmp_path / "work", {"images": denoised, "noisy": noisy},
                       AlignStageSettings(AlignConfig(), photos="noisy_first"), 0)
    with pytest.raises(_Stop):
        align(ctx)
    # the dense cloud (the splat's start) from the denoised photos
    assert calls == [(["000003.jpg", "000007.jpg"], ["000003.png", "000007.png"],
                      [("denoised", "000003.png"), ("denoised", "000007.png")])]


@pytest.mark.parametrize("refusal", [_refused("views_unsupported"),
                                     DisconnectedViewsError("disconnected", views=("000007.png",))])
def test_noisy_first_falls_back_to_the_denoised_photos_and_reports_their_refusal(tmp_path, monkeypatch, refusal):
    denoised = _views(tmp_path / "denoised", ("000003.png", "000007.png"))
    noisy = _views(tmp_path / "noisy", ("000003.png", "000007.png"))
    calls, thresholds = [], []

    def refuse_both(files, cfg, names=None, cloud_images=None):
        calls.append(files[0].parent.name)
        thresholds.append(cfg.pairwise.sensitive_below_noise)
        raise refusal if files[0].parent == noisy else _refused("positions_undetermined", ("000003.png",))

    monkeypatch.setattr(mvgeo.align, "align_images", refuse_both)
    ctx = StageContext("align", tmp_path / "work", {"images": denoised, "noisy": noisy},
                       AlignStageSettings(AlignConfig(), photos="noisy_first"), 0)
    with pytest.raises(AlignmentRefusedError) as info:
        align(ctx)
    assert calls == ["noisy", "denoised"]
    # the noisy photos with the configured detector rule, the denoised ones after them never with the
    # clean-photo (sensitive) detection from the start (`denoised_photos_config`)
    default = AlignConfig().pairwise.sensitive_below_noise
    assert default > 0 and thresholds == [default, 0.0]
    # the denoised photos' refusal is the one raised, with the pipeline's fix
    assert info.value.kind == "positions_undetermined" and info.value.fix.startswith("leave the photos ['000003']")
    # without noisy_first the noisy photos are never read
    calls.clear()
    thresholds.clear()
    plain = StageContext("align", tmp_path / "work2", {"images": denoised, "noisy": noisy},
                         AlignStageSettings(AlignConfig()), 0)
    with pytest.raises(AlignmentRefusedError):
        align(plain)
    assert calls == ["denoised"] and thresholds == [default]  # e.g. the oracle's clean photos


@pytest.mark.parametrize(("noisy_bytes", "identical"), [(b"same", True), (b"other", False)])
def test_the_stage_tells_the_alignment_whether_the_photos_were_passed_through(tmp_path, monkeypatch, noisy_bytes,
                                                                              identical):
    """`align` compares the denoised photos with the noisy ones (`same_photos`) and passes the answer on."""
    import eval.pipeline.align_stage as stage

    denoised, noisy = tmp_path / "denoised", tmp_path / "noisy"
    for folder, data in ((denoised, b"same"), (noisy, noisy_bytes)):
        folder.mkdir()
        for name in ("000003.png", "000007.png"):
            (folder / name).write_bytes(data)
    seen = []

    def record(align_images, files, noisy, cfg, *, keep_better=False, identical=False):
        seen.append((keep_better, identical))
        raise _Stop

    monkeypatch.setattr(stage, "_align_first_round", record)
    ctx = StageContext("align", tmp_path / "work", {"images": denoised, "noisy": noisy},
                       AlignStageSettings(AlignConfig(), photos="better_of"), 0)
    with pytest.raises(_Stop):
        align(ctx)
    assert seen == [(True, identical)]
