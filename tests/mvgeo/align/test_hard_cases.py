"""Hard inputs: a usable result or a specific failure, never NaN."""

from dataclasses import replace

import numpy as np
import pytest

from mvgeo.align.api import PREVIEW, align_images
from mvgeo.align.bundle import BundleConfig
from mvgeo.align.classical_pairs import ClassicalPairConfig
from mvgeo.common.errors import AlignmentRefusedError, DegenerateGeometryError, InputError
from mvgeo.common.imageio import list_images
from mvgeo.metrics import compare_poses
from mvgeo.sparse_model import read_sparse_model

FAST = replace(PREVIEW, max_size_px=160, pairwise=ClassicalPairConfig(pointmap_size_px=64),
               align=replace(PREVIEW.align, iters=60), bundle=BundleConfig(max_nfev=30))


def _usable_or_specific_failure(paths, config=FAST):
    try:
        res = align_images(paths, config)
    except (InputError, DegenerateGeometryError) as exc:
        assert len(str(exc)) > 20  # a sentence naming the problem, not a bare code
        return None
    cams = np.stack([im.cam_from_world for im in res.sparse_model.images])
    assert np.isfinite(cams).all()
    assert all(np.isfinite(c.params).all() for c in res.sparse_model.cameras.values())
    assert np.isfinite(res.points_xyz).all() and np.isfinite(res.points_conf).all()
    assert np.isfinite(res.stats.final_loss)
    return res


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    from data_synth import render_scene

    return render_scene("llff_like", tmp_path_factory.mktemp("s") / "llff", size_wh=(160, 120), views=4)


def test_two_views(small_scene):
    """Two tiny views: the focal is barely constrained, so either a usable result or the specific
    'focal length is not determined' failure; with the calibration given they must align."""
    from mvgeo.sparse_model import read_sparse_model

    paths = list_images(small_scene / "images")[:2]
    _usable_or_specific_failure(paths)
    gt = read_sparse_model(small_scene / "sparse" / "0")
    cam = gt.cameras[gt.images[0].camera_id]
    res = align_images(paths, FAST, intrinsics=cam)
    assert len(res.sparse_model.images) == 2
    ba = res.stats.bundle_adjustment
    assert ba is not None and ba.reproj_rms_after_px <= ba.reproj_rms_before_px
    assert np.isfinite(np.stack([im.cam_from_world for im in res.sparse_model.images])).all()


def test_undetermined_focal_is_a_specific_failure(small_scene):
    """4 noisy 160x120 views: no pair determines the focal and the bundle adjustment leaves ~13 %
    uncertainty (measured; the unchecked result was 30 % off): a named failure, not a wrong result."""
    with pytest.raises(DegenerateGeometryError, match="focal length is not determined"):
        align_images(list_images(small_scene / "images"), FAST)


def test_pure_rotation_is_a_specific_failure(small_scene):
    # Crops of one image = a camera rotating about its centre (approximately): no baseline. The pairs fail the
    # parallax test, or (on a 2-core Intel Xeon, where one pair's median parallax passes) the views that rest
    # on that one pair are not confirmed by PnP: a named refusal either way, never a result.
    from mvgeo.common.imageio import read_image

    img = read_image(list_images(small_scene / "images")[0])
    views = [np.ascontiguousarray(img[10:110, dx:dx + 130]) for dx in (0, 10, 20)]
    with pytest.raises((InputError, DegenerateGeometryError)) as info:
        align_images(views, FAST)
    message = str(info.value)
    assert any(reason in message for reason in ("disconnected", "rotation", "baseline",
                                                 "rest on a single verified image pair")), message


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["hard_tinybaseline", "hard_lowtexture", "hard_repetitive"])
@pytest.mark.parametrize("views", [3, 6])
def test_hard_scenes(scene, views, tmp_path):
    from data_synth import render_scene
    from mvgeo.metrics import compare_poses
    from mvgeo.sparse_model import read_sparse_model

    d = render_scene(scene, tmp_path / scene, size_wh=(256, 192), views=views)
    res = _usable_or_specific_failure(list_images(d / "images"))
    if res is not None:  # a result is a right one: no relative rotation more than 5 deg off (issue 21's bound)
        gt = read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()
        m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt)
        assert m.n_registered == len(res.sparse_model.images) and float(np.max(m.rotation_deg)) <= 5.0, m.summary()


def test_known_intrinsics_from_colmap_cameras_txt(small_scene, tmp_path):
    from mvgeo.align.intrinsics import read_intrinsics
    from mvgeo.sparse_model import read_sparse_model, write_sparse_model

    gt = read_sparse_model(small_scene / "sparse" / "0")
    write_sparse_model(tmp_path / "m", gt, binary=False)
    cam = read_intrinsics(tmp_path / "m" / "cameras.txt")
    known = align_images(list_images(small_scene / "images"), FAST, intrinsics=cam)
    assert known.stats.known_intrinsics
    for c in known.sparse_model.cameras.values():  # written unchanged at the input resolution
        np.testing.assert_allclose(c.params, cam.K[[0, 1, 0, 1], [0, 1, 2, 2]])
    assert np.isfinite(np.stack([im.cam_from_world for im in known.sparse_model.images])).all()


def test_unknown_intrinsics_format_is_input_error(tmp_path):
    from mvgeo.align.intrinsics import read_intrinsics

    (tmp_path / "cam.yaml").write_text("fx: 1")
    with pytest.raises(InputError, match="unknown intrinsics format"):
        read_intrinsics(tmp_path / "cam.yaml")


@pytest.mark.parametrize(("params", "message"), [
    ("0 0 64 48", "focal length fx = 0 px: it must be positive"),
    ("-100 -100 64 48", "focal length fx = -100 px: it must be positive"),
    ("100 -100 64 48", "focal length fy = -100 px"),
    ("1e308 1e308 64 48", "at most 100 times the image's long side"),
])
def test_a_camera_no_lens_has_is_refused_naming_the_file(tmp_path, params, message):
    """A zero focal used to make the two-view geometry singular (a traceback), a negative one failed later as
    a diverged alignment or a disconnected pair graph; both only after `denoise-gs run`'s denoising."""
    from mvgeo.align.intrinsics import read_intrinsics

    path = tmp_path / "cameras.txt"
    path.write_text(f"1 PINHOLE 128 96 {params}\n")
    with pytest.raises(InputError, match=message) as refused:
        read_intrinsics(path)
    assert str(path) in str(refused.value)
    path.write_text("1 PINHOLE 128 96 100 100 64 48\n")
    assert read_intrinsics(path).fx == 100.0


@pytest.mark.slow
def test_orbit_view_with_undetermined_position_is_a_specific_failure(tmp_path):
    """object_ring's 21 training views at 256x192 (24-view ring, every 8th view held out: 15 deg steps with
    three 30 deg gaps). View 15 is tied to the rest by two-view tracks with views 14 and 17, which lie on
    nearly one line with it; the whole-result check passed a result that put it 4 m off on a 3 m ring
    (measured). The alignment refuses the ring, naming views at its gaps."""
    import json

    from data_synth import render_scene
    from mvgeo.align.api import AlignConfig
    from mvgeo.align.dense_stereo import DenseStereoConfig

    d = render_scene("object_ring", tmp_path / "ring", size_wh=(256, 192))
    split = json.loads((d / "split.json").read_text())
    train = split["train"]
    paths = [p for p in list_images(d / "images") if p.name in train]
    cfg = replace(AlignConfig(), dense_stereo=DenseStereoConfig(enabled=False))
    # Which check names which view depends on the machine (SIFT's floating point differs between CPUs): on
    # one AMD EPYC the position check named view 15 (its ratio 19, the others <= 0.024); on an AMD EPYC Zen 4
    # the view-support check (ratio 0.14, but both of its pairs inconsistent: 70 % explained and 24 deg off,
    # 30 %); on a 2-core Intel Xeon the single-pair check named view 7, at the gap where the unchecked result
    # breaks (views 9-14 turned 24 deg as a group). Each names views that border a gap of the ring. Both starts
    # are solved (the first one's candidates all refused); where the other start's refusal explains more
    # matches it is the one reported, and it can name a group hinged at a gap with the views that border it
    # (on an AMD EPYC: view 7 on its pair with view 6, views 9-15 on the pair (9, 10)).
    with pytest.raises(AlignmentRefusedError) as info:
        align_images(paths, cfg)
    assert info.value.kind in ("views_unsupported", "positions_undetermined"), info.value
    def ring_index(name: str) -> int:  # view_007.png -> 7
        return int(name.split("_")[1].split(".")[0])

    held = {ring_index(n) for n in split["test"]}
    at_gap = {n for n in train if (ring_index(n) - 1) % 24 in held or (ring_index(n) + 1) % 24 in held}
    named = set(info.value.views)
    def steps(a: str, b: str) -> int:  # along the ring of 24
        d = abs(ring_index(a) - ring_index(b))
        return min(d, 24 - d)

    between = {n for n in train if any(steps(n, g) < 8 for g in named & at_gap)}  # up to the next gap
    assert named & at_gap and named <= between, (info.value.views, sorted(at_gap))
    # With both checks off a result is returned, and it is wrong: the refusal is right. (How view 15 shows it
    # depends on the render and the CPU: not pinned, its centre ratio 19 against <= 0.024 for the others; both
    # of its pairs inconsistent; or, on the render with view-independent silhouette shading, pinned (0.057) with
    # its pair with view 17 31 deg off, the ring 20 deg off at worst, 2.4 deg median.)
    res = align_images(paths, replace(cfg, max_centre_std_ratio=0.0, reject_unsupported_views=False))
    ref = {im.name: im.cam_from_world for im in read_sparse_model(d / "sparse" / "0").images}
    est = {im.name: im.cam_from_world for im in res.sparse_model.images}
    errors = compare_poses(est, {n: ref[n] for n in train})
    assert errors.rotation_deg.max() > 5.0, (errors.median_rotation_deg, res.stats.pairs_inconsistent)
    assert any("view_015.png" in (p.i, p.j) for p in res.stats.pairs_inconsistent), res.stats.pairs_inconsistent


@pytest.mark.slow
def test_denser_orbit_is_registered_or_its_unsupported_view_named(tmp_path):
    """object_ring with 32 views at 256x192: 28 training views (11.25 deg steps, four 22.5 deg gaps).

    Defaults (relative poses refined by LM on their inliers, `TwoViewConfig.refine`): every view registered,
    measured 0.57 deg median relative rotation error, 2.4 deg max, ATE 0.028 m on the 3 m ring.
    With the raw USAC relative poses (refine off) view_001's pairs are contradicted: without the view-support
    check (`reject_unsupported_views`) `mvgeo align` returned it 6.3 m off (ATE 1.39 m, 3.6 deg); with it the
    alignment is refused (view_001 cut off, and the views beside it that hang on one weak pair), and
    `allow_partial` registers a subset that is right (measured 14 of 28 at 0.66 deg, ATE 0.015 m). The bounds
    (1.5 deg, 0.05 m) lie between these and the bent results seen on this ring (3.6-5.1 deg, ATE 0.11-1.39 m).
    PnP on the other views' points places view_001 elsewhere (77 inliers), but re-posing it there bends the
    rest of the ring by 6.5 deg (`mvgeo.align.solve.relocate`: not kept); kept, that result was 5.8 deg median,
    22 deg max, every pair explained."""
    import json

    from data_synth import render_scene
    from mvgeo.align.api import AlignConfig
    from mvgeo.align.dense_stereo import DenseStereoConfig
    from mvgeo.metrics import compare_poses
    from mvgeo.sparse_model import read_sparse_model

    d = render_scene("object_ring", tmp_path / "ring", size_wh=(256, 192), views=32)
    train = json.loads((d / "split.json").read_text())["train"]
    paths = [p for p in list_images(d / "images") if p.name in train]
    gt = read_sparse_model(d / "sparse" / "0").cam_from_world_by_name()
    cfg = replace(AlignConfig(), dense_stereo=DenseStereoConfig(enabled=False))
    try:
        m = compare_poses(align_images(paths, cfg).sparse_model.cam_from_world_by_name(), gt)
        assert m.n_registered == 28
    except AlignmentRefusedError as exc:
        # The other outcome this ring has, measured on an Intel Xeon (the runs on an AMD EPYC registered all
        # 28: the two machines' floating-point rounding differs, and the ring is at the edge): views 009-015 hang on the
        # 20-match pair (015, 017) once the pair (007, 009) is contradicted, view_015 comes out 3.6 deg off
        # (the others 0.1-1.4 deg), and PnP on the other views' points puts it 3.7 deg from there, so the
        # group is refused as unconfirmed. The refusal must name it, and the rest must register correctly.
        assert exc.kind == "views_unsupported" and "view_015.png" in str(exc)
        m = compare_poses(align_images(paths, replace(cfg, allow_partial=True)).sparse_model
                          .cam_from_world_by_name(), gt)
        assert m.n_registered >= 14
    assert m.median_rotation_deg < 1.5 and m.ate.rmse < 0.05
    raw = replace(cfg, pairwise=replace(cfg.pairwise, two_view=replace(cfg.pairwise.two_view, refine=False)))
    try:
        # The chained start's candidates are refused for unsupported views (view_001 cut off by contradicted
        # pairs, and the half of the ring that hangs on one weak pair beside it); the averaged start, solved
        # since, registered all 28 on an AMD EPYC (0.47 deg median, worst view 1.1 deg, ATE 0.023 m).
        res = align_images(paths, raw)
        assert [c.start for c in res.stats.candidates][0] == "chain" and not res.stats.candidates[0].chosen
    except AlignmentRefusedError as exc:  # where both starts are refused (chained: "view_002.png" named first)
        assert exc.kind == "views_unsupported", exc
        res = align_images(paths, replace(raw, allow_partial=True))
    m = compare_poses(res.sparse_model.cam_from_world_by_name(), gt)
    assert m.n_registered >= 3
    assert m.median_rotation_deg < 1.5 and m.ate.rmse < 0.05
