"""Working resolution (`--max-size`): the size rule, the area filter against a slow reference, the
pipeline's working images and report, cameras scaled back to the input size, the eval dataset, and
(slow) the full `denoise-gs run` on 384x288 photos rendering at 192x144."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from eval.cli import build_parser
from eval.pipeline import PipelineConfig, run_pipeline
from eval.pipeline.inputs import (
    SIZES_FILE,
    WORKING_DIR,
    nearest_depth,
    resize_area,
    working_dataset,
    working_size,
)
from eval.pipeline.publish import input_size_cameras
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model
from tests.eval._tiny_stages import TinyStages, make_scene


@pytest.mark.parametrize(("wh", "max_size", "expected"), [
    ((384, 288), 192, (192, 144)),
    ((288, 384), 192, (144, 192)),  # portrait: the long side is the height
    ((4000, 3000), 512, (512, 384)),
    ((1000, 333), 512, (512, 170)),  # 333 * 0.512 = 170.5 -> 170
    ((300, 200), 512, (300, 200)),  # never upscaled
    ((384, 288), None, (384, 288)),
])
def test_working_size(wh, max_size, expected):
    assert working_size(*wh, max_size) == expected


def test_area_filter_is_the_block_mean_for_an_integer_factor(rng):
    img = rng.random((288, 384, 3)).astype(np.float32)
    small = resize_area(img, (192, 144))
    # slow obvious reference: each output pixel is the mean of its 2x2 input block
    ref = np.empty((144, 192, 3), np.float64)
    for y in range(144):
        for x in range(192):
            ref[y, x] = img[2 * y:2 * y + 2, 2 * x:2 * x + 2].reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(small, ref, atol=1e-6)
    assert resize_area(img, (384, 288)) is img
    with pytest.raises(ValueError, match="only downscales"):
        resize_area(img, (400, 300))


def _cfg(**kw) -> PipelineConfig:
    return PipelineConfig(views=3, rounds=1, **kw)


def test_pipeline_works_at_the_working_size_and_reports_it(tmp_path):
    scene = make_scene(tmp_path / "photos", n=4, size_wh=(384, 288))
    out = tmp_path / "out"
    res = run_pipeline(scene, out, _cfg(max_size=192), stages=TinyStages().stages())
    working = sorted((out / WORKING_DIR).glob("*.png"))
    assert len(working) == 4
    for p in working:
        assert read_image(p).shape == (144, 192, 3)
    for p in (out / "round1" / "renders").glob("*.png"):
        assert read_image(p).shape == (144, 192, 3)
    sizes = json.loads((out / WORKING_DIR / SIZES_FILE).read_text())
    assert sizes["view_000"] == {"input": [384, 288], "working": [192, 144], "focal_35mm": None,  # PNG, no EXIF
                                 "file": "view_000.png"}
    # the working image is the area-filtered input
    np.testing.assert_allclose(read_image(out / WORKING_DIR / "view_000.png"),
                               resize_area(read_image(scene / "view_000.png"), (192, 144)), atol=1 / 65535)
    md = res.report_md.read_text()
    assert "working size: 192x144 (from 384x288)" in md and "--max-size: long side <= 192 px" in md
    report = json.loads(res.report_json.read_text())
    assert report["max_size"] == 192 and report["image_sizes"]["view_001"]["working"] == [192, 144]


def test_changing_max_size_reruns_from_the_working_images(tmp_path):
    scene = make_scene(tmp_path / "photos", n=4, size_wh=(96, 64))
    out, tiny = tmp_path / "out", TinyStages()
    run_pipeline(scene, out, _cfg(max_size=64), stages=tiny.stages())
    run_pipeline(scene, out, _cfg(max_size=64), stages=tiny.stages())
    assert tiny.calls["denoise"] == 1  # resumed
    run_pipeline(scene, out, _cfg(max_size=48), stages=tiny.stages())
    assert tiny.calls["denoise"] == 2
    assert read_image(out / "round1" / "renders" / "view_000.png").shape == (32, 48, 3)


def test_a_max_size_that_leaves_too_few_pixels_is_refused(tmp_path):
    scene = make_scene(tmp_path / "photos", n=3, size_wh=(400, 40))
    with pytest.raises(InputError, match="max-size"):
        run_pipeline(scene, tmp_path / "out", _cfg(max_size=100), stages=TinyStages().stages())
    assert not (tmp_path / "out" / WORKING_DIR).exists()


def test_cameras_scaled_to_the_input_size():
    cam = Camera.pinhole(180.0, 170.0, 96.5, 71.0, 192, 144)
    pose = np.hstack([np.eye(3), [[0.1], [0.2], [0.3]]])
    sparse = SparseModel({1: cam}, [PosedImage("a.png", 1, pose), PosedImage("b.png", 1, pose),
                                    PosedImage("c.png", 1, pose)])
    sizes = {"a": {"input": (384, 288), "working": (192, 144)}, "b": {"input": (384, 288), "working": (192, 144)},
             "c": {"input": (768, 576), "working": (192, 144)}}
    full = input_size_cameras(sparse, sizes)
    a, c = full.camera_of("a.png"), full.camera_of("c.png")
    assert full.image("a.png").camera_id == full.image("b.png").camera_id != full.image("c.png").camera_id
    assert (a.width, a.height, c.width, c.height) == (384, 288, 768, 576)
    # pixel quantities scale by W_in / W_work: a point projects to 2x (4x) its working-image pixel
    X = np.array([0.3, -0.2, 2.0])  # camera frame
    uv_work = cam.project(X).uv_px
    np.testing.assert_allclose(a.project(X).uv_px, 2 * uv_work, rtol=1e-12)
    np.testing.assert_allclose(c.project(X).uv_px, 4 * uv_work, rtol=1e-12)
    np.testing.assert_array_equal(full.image("c.png").cam_from_world, pose)
    with pytest.raises(InputError, match="differs"):
        input_size_cameras(sparse, {**sizes, "a": {"input": (384, 288), "working": (100, 75)}})


def _eval_dataset(root):
    """Three 96x64 views (noisy, clean, their cameras), two for training: an evaluation dataset folder."""
    make_scene(root / "images", n=3, size_wh=(96, 64))
    make_scene(root / "clean", n=3, size_wh=(96, 64), seed=1)
    cam = Camera.pinhole(80.0, 80.0, 48.0, 32.0, 96, 64)
    imgs = [PosedImage(f"view_{i:03d}.png", 1, np.hstack([np.eye(3), [[i * 0.1], [0], [0]]])) for i in range(3)]
    write_sparse_model(root / "sparse" / "0", SparseModel({1: cam}, imgs), binary=False)
    (root / "split.json").write_text(json.dumps({"train": ["view_000", "view_001"], "test": ["view_002"]}))
    return root


def test_eval_dataset_is_scaled_with_its_cameras(tmp_path):
    root = _eval_dataset(tmp_path / "ds")
    assert working_dataset(root, tmp_path / "out", 96) == root  # nothing above the limit: used as is
    small = working_dataset(root, tmp_path / "out", 48)
    assert small == tmp_path / "out" / "data" / "ds_max48"
    assert read_image(small / "images" / "view_000.png").shape == (32, 48, 3)
    assert read_image(small / "clean" / "view_002.png").shape == (32, 48, 3)
    scaled = read_sparse_model(small / "sparse" / "0").camera_of("view_000.png")
    assert (scaled.width, scaled.height, scaled.fx, scaled.cx) == (48, 32, 40.0, 24.0)
    assert json.loads((small / "split.json").read_text())["test"] == ["view_002"]
    assert working_dataset(root, tmp_path / "out", 48) == small  # reused
    assert not (small / "depth").exists()  # none to copy


def test_eval_dataset_is_made_again_when_its_source_changes_and_takes_its_depth_maps(tmp_path):
    root = _eval_dataset(tmp_path / "ds")
    (root / "depth").mkdir()
    depth = np.arange(64 * 96, dtype=np.float32).reshape(64, 96)
    depth[:10, :10] = np.inf  # misses stay misses
    for i in range(3):
        np.save(root / "depth" / f"view_{i:03d}.npy", depth + i)
    small = working_dataset(root, tmp_path / "out", 48)
    d = np.load(small / "depth" / "view_001.npy")
    assert d.shape == (32, 48) and np.array_equal(d, nearest_depth(depth + 1, (48, 32)))
    assert np.isinf(d[:5, :5]).all()
    before = read_image(small / "images" / "view_000.png")
    # The dataset at the same path is replaced by another (e.g. rendered again): the working copy follows it.
    shutil.rmtree(root / "images")
    make_scene(root / "images", n=3, size_wh=(96, 64), seed=7)
    assert working_dataset(root, tmp_path / "out", 48) == small
    after = read_image(small / "images" / "view_000.png")
    assert not np.array_equal(before, after)
    np.testing.assert_allclose(after, resize_area(read_image(root / "images" / "view_000.png"), (48, 32)),
                               atol=1 / 65535)


def test_eval_dataset_is_made_again_by_changed_code(tmp_path, monkeypatch):
    """The working-size dataset records the code that made it: with another area filter (an edit of
    `eval.pipeline` or `mvgeo`, a new source digest) it is made again, not reused from the old code."""
    import eval.pipeline.inputs as inputs_mod

    root = _eval_dataset(tmp_path / "ds")
    small = working_dataset(root, tmp_path / "out", 48)
    before = read_image(small / "images" / "view_000.png")
    assert working_dataset(root, tmp_path / "out", 48) == small  # reused by the same code

    def nearest(img, size_wh):
        return np.ascontiguousarray(img[::2, ::2]) if img.shape[1] != size_wh[0] else img

    monkeypatch.setattr(inputs_mod, "resize_area", nearest)
    monkeypatch.setattr(inputs_mod, "_dataset_code", lambda: {"eval.pipeline": "edited", "mvgeo": "edited"})
    assert working_dataset(root, tmp_path / "out", 48) == small
    after = read_image(small / "images" / "view_000.png")
    assert not np.array_equal(before, after)
    np.testing.assert_allclose(after, read_image(root / "images" / "view_000.png")[::2, ::2], atol=1 / 65535)


def test_nearest_depth_against_a_loop(rng):
    depth = rng.random((7, 10)).astype(np.float32)
    for wh in [(5, 3), (10, 7), (4, 4)]:
        ref = np.empty((wh[1], wh[0]), np.float32)
        for y in range(wh[1]):
            for x in range(wh[0]):  # the input pixel under the output pixel's centre
                ref[y, x] = depth[int((y + 0.5) * 7 / wh[1]), int((x + 0.5) * 10 / wh[0])]
        assert np.array_equal(nearest_depth(depth, wh), ref)


def test_cli_max_size_values():
    parser = build_parser()
    assert parser.parse_args(["run", "p", "--out", "o"]).max_size == 512
    assert parser.parse_args(["run", "p", "--out", "o", "--max-size", "0"]).max_size is None
    assert parser.parse_args(["eval", "s", "--out", "o", "--max-size", "256"]).max_size == 256
    with pytest.raises(SystemExit):
        parser.parse_args(["run", "p", "--out", "o", "--max-size", "16"])


@pytest.mark.slow  # the real pipeline (fast preset, one round) on 6 rendered views: 10 min on a loaded 2-core box
@pytest.mark.timeout(1800)
def test_denoise_gs_run_max_size_192_on_384x288_photos(tmp_path):
    from data_synth import render_scene  # noqa: PLC0415  (open3d: slow import)
    from eval.cli import main
    from splat.export import SPLAT_BYTES_PER_GAUSSIAN
    from splat.ply import read_gaussian_ply

    data = tmp_path / "data"
    render_scene("llff_like", data, size_wh=(384, 288), views=6)
    photos = tmp_path / "photos"
    shutil.copytree(data / "images", photos)
    out = tmp_path / "out"
    assert main(["run", str(photos), "--out", str(out), "--max-size", "192", "--preset", "fast",
                 "--rounds", "1", "--views", "4"]) == 0
    renders = sorted((out / "round1" / "renders").glob("*.png"))
    assert renders and all(read_image(p).shape == (144, 192, 3) for p in renders)
    n = read_gaussian_ply(out / "round1" / "point_cloud.ply").num_gaussians
    assert (out / "scene.splat").stat().st_size == SPLAT_BYTES_PER_GAUSSIAN * n
    assert "__VISER_EMBED_DATA__" in (out / "view" / "index.html").read_text()
    full = read_sparse_model(out / "cameras" / "input")
    assert {(c.width, c.height) for c in full.cameras.values()} == {(384, 288)}
    md = (out / "report.md").read_text()
    assert "(scene.splat)" in md and "(view/index.html)" in md and "192x144 (from 384x288)" in md
