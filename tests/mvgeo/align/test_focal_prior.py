"""The focal length prior: photos whose EXIF gives one focal start the pairs there (no pair-focal consensus, no
re-estimation when it is right), and every other case keeps the estimate from the pairs."""

import dataclasses

import numpy as np
import pytest

from mvgeo.align.api import PREVIEW, align_images
from mvgeo.align.classical_pairs import ClassicalPointmapModel
from mvgeo.align.intrinsics import FULL_FRAME_DIAGONAL_MM, FocalPrior
from mvgeo.align.stats import AlignStats
from mvgeo.common.errors import AlignmentRefusedError, InputError
from mvgeo.common.imageio import list_images, read_image
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model

Image = pytest.importorskip("PIL.Image")


@pytest.fixture(scope="module")
def llff6_exif(llff6, tmp_path_factory):
    """`llff6`'s PNGs with the EXIF 35 mm-equivalent focal a camera would write for them (whole millimetres,
    as the tag is an integer), the same pixels. Returns (folder, true focal px, EXIF focal px)."""
    gt = read_sparse_model(llff6 / "sparse" / "0")
    cam = gt.camera_of(gt.names[0])
    f_true = cam.params[0]  # 208.9 px at 256x192
    f35 = round(f_true * FULL_FRAME_DIAGONAL_MM / np.hypot(cam.width, cam.height))  # 28 mm
    out = tmp_path_factory.mktemp("llff6_exif")
    for p in list_images(llff6 / "images"):
        exif = Image.Exif()
        exif.get_ifd(0x8769)[0xA405] = f35
        with Image.open(p) as im:
            im.save(out / p.name, exif=exif.tobytes())
    return out, f_true, FocalPrior(float(f35)).focal_px((cam.width, cam.height))


def test_an_exif_focal_starts_the_pairs_and_needs_no_re_estimation(llff6, llff6_exif, llff6_preview):
    folder, f_true, f_exif = llff6_exif
    for p in list_images(folder):  # the pixels are llff6's: only the prior differs
        np.testing.assert_array_equal(read_image(p), read_image(llff6 / "images" / p.name))
    res = align_images(list_images(folder), dataclasses.replace(PREVIEW, seed=0))
    s = res.stats
    assert s.focal_prior is not None and s.focal_prior.source == "exif" and s.focal_prior.focal_35mm == 28.0
    assert s.focal_prior.focal_px == pytest.approx(f_exif, abs=0.01)  # 207.1 px, 0.9 % under the truth
    # The first candidate's pairs used it (at the alignment size, here the input size) and the bundle
    # adjustment kept it within `refocus_min_change`: one candidate, where the pair-focal consensus and
    # COLMAP's prior needed a re-estimation (llff6_preview: 307 -> 205 px, two candidates).
    assert [(c.pairs_focal_px, c.refocused, c.chosen) for c in s.candidates] == [(round(f_exif, 2), False, True)]
    assert len(llff6_preview.stats.candidates) == 2 and llff6_preview.stats.focal_prior is None
    assert "have no EXIF" in llff6_preview.stats.focal_prior_unavailable
    f = res.sparse_model.camera_of(res.sparse_model.names[0]).params[0]
    assert abs(f / f_true - 1.0) < 0.05  # measured 2.6 % (the re-estimated run: the same 203.4 px)
    gt = read_sparse_model(llff6 / "sparse" / "0")
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt.cam_from_world_by_name())
    ref = compare_poses(llff6_preview.sparse_model.cam_from_world_by_name(), gt.cam_from_world_by_name())
    assert m.n_registered == 6 and m.median_rotation_deg < max(0.5, 2 * ref.median_rotation_deg), (m, ref)
    # align.json carries the prior and reads back
    back = AlignStats.from_json(s.to_json())
    assert back.focal_prior == s.focal_prior


def test_the_exif_focal_can_be_switched_off(llff6_exif):
    folder, _, _ = llff6_exif
    res = align_images(list_images(folder), dataclasses.replace(PREVIEW, seed=0, exif_focal=False))
    assert res.stats.focal_prior is None and "exif_focal off" in res.stats.focal_prior_unavailable
    assert res.stats.candidates[0].pairs_focal_px == pytest.approx(1.2 * 256)  # COLMAP's prior, as without EXIF


def test_a_given_prior_applies_to_arrays_and_a_custom_model_refuses_it(llff6):
    files = list_images(llff6 / "images")
    arrays = [read_image(p) for p in files]
    prior = FocalPrior(28.0)
    model = ClassicalPointmapModel(PREVIEW.pairwise, seed=0)
    with pytest.raises(InputError, match="custom pair model"):
        align_images(arrays, PREVIEW, model=model, focal_prior=prior)
    with pytest.raises(ValueError, match="positive"):
        ClassicalPointmapModel(PREVIEW.pairwise, focal_prior_px=-1.0)
    res = align_images(arrays, dataclasses.replace(PREVIEW, seed=0), focal_prior=prior)
    assert res.stats.focal_prior.source == "given"
    assert res.stats.candidates[0].pairs_focal_px == pytest.approx(prior.focal_px((256, 192)), abs=0.01)


def test_an_older_align_json_without_the_prior_still_reads(llff6_preview):
    data = llff6_preview.stats.to_json()
    for key in ("focal_prior", "focal_prior_unavailable", "views_located_by_points"):
        data.pop(key)
    back = AlignStats.from_json(data)
    assert back.focal_prior is None and back.focal_prior_unavailable == "" and back.views_located_by_points == []
    # nothing else changes: the defaults stand for the missing keys
    assert back == dataclasses.replace(llff6_preview.stats, focal_prior=None, focal_prior_unavailable="",
                                       views_located_by_points=[])
    with pytest.raises(KeyError, match="n_images"):
        AlignStats.from_json({k: v for k, v in data.items() if k != "n_images"})


def test_a_prior_the_adjustment_keeps_determines_the_focal(llff6_exif):
    """With a focal-uncertainty limit no adjustment meets, the pairs' own focal (not determined on llff6:
    too few agreeing pairs) is refused; the EXIF prior, kept by the adjustment within 10 %, is not."""
    folder, _, _ = llff6_exif
    strict = dataclasses.replace(PREVIEW, seed=0, max_focal_log_std=1e-9)
    with pytest.raises(AlignmentRefusedError) as info:
        align_images(list_images(folder), dataclasses.replace(strict, exif_focal=False))
    assert info.value.kind == "focal_undetermined" and "--no-exif-focal" not in info.value.fix
    res = align_images(list_images(folder), strict)
    assert res.stats.focal_prior is not None and res.stats.n_registered == 6
    # a prior far from what the adjustment finds (2x) is not kept: refused, and the fix names the EXIF
    with pytest.raises(AlignmentRefusedError) as info:
        align_images(list_images(folder), strict, focal_prior=FocalPrior(56.0))
    assert info.value.kind == "focal_undetermined" and "--no-exif-focal" in info.value.fix
