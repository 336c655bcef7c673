"""Photos turned by 90 degrees (portrait among landscape): the run turns their working images to the common
orientation and turns their cameras back in `cameras/input/`; `turn_back` against `np.rot90` itself."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eval.pipeline import PipelineConfig, run_pipeline
from eval.pipeline.inputs import SIZES_FILE, WORKING_DIR, read_sizes, reference_working_size, resize_area
from eval.pipeline.publish import input_size_cameras, turn_back
from eval.pipeline.validate import validate_run_inputs
from mvgeo.camera import Camera
from mvgeo.common.errors import InputError
from mvgeo.common.imageio import read_image, write_image
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model
from tests.eval._tiny_stages import TinyStages, make_scene


def _quarter_turn_pixel_map(width_a: int, height_a: int) -> np.ndarray:
    """(2, 3) affine map from pixel centres of B = np.rot90(A) to those of A, fitted from np.rot90 of an
    index image (the reference: no formula of ours in it)."""
    a = np.arange(width_a * height_a).reshape(height_a, width_a)
    b = np.rot90(a)
    rb, cb = np.mgrid[:b.shape[0], :b.shape[1]]
    ra, ca = np.divmod(b, width_a)
    src = np.stack([cb.ravel() + 0.5, rb.ravel() + 0.5, np.ones(b.size)], axis=1)
    dst = np.stack([ca.ravel() + 0.5, ra.ravel() + 0.5], axis=1)
    m, *_ = np.linalg.lstsq(src, dst, rcond=None)
    np.testing.assert_allclose(src @ m, dst, atol=1e-9)  # exactly affine
    return m.T


def test_turn_back_matches_np_rot90():
    rng = np.random.default_rng(0)
    cam_b = Camera.pinhole(100.0, 90.0, 30.3, 22.7, 64, 48)  # the working image B, landscape
    pose_b = np.hstack([Rotation.random(random_state=1).as_matrix(), rng.normal(size=(3, 1))])
    cam_a, pose_a = turn_back(cam_b, pose_b)
    assert (cam_a.width, cam_a.height) == (48, 64)  # the photo A, portrait
    m = _quarter_turn_pixel_map(cam_a.width, cam_a.height)
    X_world = rng.normal(size=(50, 3))
    X_b = X_world @ pose_b[:, :3].T + pose_b[:, 3]
    X_world, X_b = X_world[X_b[:, 2] > 0.1], X_b[X_b[:, 2] > 0.1]
    uv_b = cam_b.project(X_b).uv_px
    uv_a = cam_a.project(X_world @ pose_a[:, :3].T + pose_a[:, 3]).uv_px
    np.testing.assert_allclose(uv_a, np.c_[uv_b, np.ones(len(uv_b))] @ m.T, atol=1e-9)
    # The same camera centre: a turn about the optical axis.
    centre = lambda p: -p[:, :3].T @ p[:, 3]  # noqa: E731
    np.testing.assert_allclose(centre(pose_a), centre(pose_b), atol=1e-12)
    with pytest.raises(InputError, match="lens distortion"):
        turn_back(Camera("SIMPLE_RADIAL", 64, 48, [100.0, 32.0, 24.0, 0.1]), pose_b)


def test_input_size_cameras_turn_back_the_turned_views():
    cam = Camera.pinhole(180.0, 170.0, 96.5, 71.0, 192, 144)
    pose = np.hstack([np.eye(3), [[0.1], [0.2], [0.3]]])
    sparse = SparseModel({1: cam}, [PosedImage(f"{n}.png", 1, pose) for n in "abc"])
    sizes = {"a": {"input": (384, 288), "working": (192, 144), "turned": 0},
             "b": {"input": (288, 384), "working": (192, 144), "turned": 1},
             "c": {"input": (384, 288), "working": (192, 144)}}  # an older sizes.json: no "turned"
    full = input_size_cameras(sparse, sizes)
    a, b = full.camera_of("a.png"), full.camera_of("b.png")
    assert full.image("a.png").camera_id == full.image("c.png").camera_id != full.image("b.png").camera_id
    assert (b.width, b.height) == (288, 384)
    turned_cam, turned_pose = turn_back(cam, pose)
    ref = turned_cam.scaled(288, 384)
    assert (b.model, b.width, b.height) == (ref.model, ref.width, ref.height)
    np.testing.assert_array_equal(b.params, ref.params)
    np.testing.assert_array_equal(full.image("b.png").cam_from_world, turned_pose)
    np.testing.assert_array_equal(full.image("a.png").cam_from_world, pose)
    np.testing.assert_array_equal(a.params, cam.scaled(384, 288).params)


def test_reference_working_size_is_the_most_common():
    assert reference_working_size([(64, 48), (48, 64), (64, 48)]) == (64, 48)
    assert reference_working_size([(48, 64), (48, 64), (64, 48)]) == (48, 64)
    assert reference_working_size([(48, 64), (64, 48)]) == (48, 64)  # a tie: the first


def _turn(path, k: int = 1):
    write_image(path, np.ascontiguousarray(np.rot90(read_image(path), k=k)))


def test_run_turns_a_portrait_photo_and_writes_its_camera_turned_back(tmp_path):
    scene = make_scene(tmp_path / "photos", n=4, size_wh=(64, 48))
    _turn(scene / "view_002.png", k=-1)  # a photo taken with the camera turned the other way
    out = tmp_path / "out"
    res = run_pipeline(scene, out, PipelineConfig(views=3, rounds=1), stages=TinyStages().stages())
    sizes = json.loads((out / WORKING_DIR / SIZES_FILE).read_text())
    assert sizes["view_002"]["working"] == [64, 48] and sizes["view_002"]["input"] == [48, 64]
    assert sizes["view_002"]["turned"] == 1 and "turned" not in sizes["view_001"]
    assert read_sizes(out / WORKING_DIR / SIZES_FILE)["view_001"]["turned"] == 0
    np.testing.assert_allclose(read_image(out / WORKING_DIR / "view_002.png"),
                               np.rot90(read_image(scene / "view_002.png")), atol=1 / 65535)
    for p in (out / "round1" / "renders").glob("*.png"):
        assert read_image(p).shape == (48, 64, 3)
    # What the export stage writes as cameras/input/ (the tiny stages have no Gaussians to export).
    working = read_sparse_model(out / "round1" / "sparse" / "0")
    full = input_size_cameras(working, read_sizes(out / WORKING_DIR / SIZES_FILE))
    assert (full.camera_of("view_002.png").width, full.camera_of("view_002.png").height) == (48, 64)
    assert (full.camera_of("view_001.png").width, full.camera_of("view_001.png").height) == (64, 48)
    cam, pose = turn_back(working.camera_of("view_002.png"), working.image("view_002.png").cam_from_world)
    np.testing.assert_allclose(full.image("view_002.png").cam_from_world, pose, atol=1e-12)
    assert "turned a quarter counter-clockwise" in res.report_md.read_text() and "view_002" in res.report_md.read_text()


def test_turned_photos_with_a_calibration_or_other_sizes_are_refused(tmp_path):
    scene = make_scene(tmp_path / "photos", n=4, size_wh=(64, 48))
    _turn(scene / "view_001.png")
    cfg = PipelineConfig(views=3, rounds=1)
    assert list(validate_run_inputs(scene, cfg)) == ["view_000", "view_001", "view_002", "view_003"]
    cams = tmp_path / "cameras.txt"
    cams.write_text("1 PINHOLE 64 48 60 60 32 24\n")
    with_calibration = dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, intrinsics=str(cams)))
    with pytest.raises(InputError, match="rotate the photos to the calibration's orientation"):
        validate_run_inputs(scene, with_calibration)
    write_image(scene / "view_003.png", resize_area(read_image(scene / "view_000.png"), (48, 36)))
    with pytest.raises(InputError, match="resize or crop"):
        validate_run_inputs(scene, cfg)


def test_an_evaluation_dataset_of_two_orientations_is_refused(tmp_path):
    """An evaluation scores poses in each photo's own frame, which turning would change: refused up front."""
    from eval.pipeline import validate_dataset_folder

    root = tmp_path / "ds"
    scene = make_scene(root / "images", n=4, size_wh=(64, 48))
    make_scene(root / "clean", n=4, size_wh=(64, 48))
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "split.json").write_text(json.dumps({"train": [f"view_00{i}.png" for i in range(3)],
                                                 "test": ["view_003.png"]}))
    assert validate_dataset_folder(root).train == ["view_000", "view_001", "view_002"]
    _turn(scene / "view_001.png")
    with pytest.raises(InputError, match="two orientations.*view_000: 64x48, view_001: 48x64"):
        validate_dataset_folder(root)


def test_a_turned_photo_that_is_also_downscaled_is_reported_as_resized(tmp_path):
    scene = make_scene(tmp_path / "photos", n=3, size_wh=(128, 96))
    _turn(scene / "view_001.png")
    out = tmp_path / "out"
    run_pipeline(scene, out, PipelineConfig(views=3, rounds=1, max_size=64), stages=TinyStages().stages())
    summary = json.loads((out / "stages" / "inputs.json").read_text())["summary"]
    assert summary["turned"] == ["view_001"] and summary["resized"] == ["view_000", "view_001", "view_002"]
    assert json.loads((out / WORKING_DIR / SIZES_FILE).read_text())["view_001"] == {
        "input": [96, 128], "working": [64, 48], "focal_35mm": None, "turned": 1, "file": "view_001.png"}


def test_input_size_cameras_name_the_photos_files(tmp_path):
    """`cameras/input/` is for the photos as they are: each camera is named as its photo is in the input
    folder (a JPEG, an upper-case suffix), not as the working PNG, so COLMAP and other tools pointed at the
    photos find them. A `sizes.json` that does not record the file keeps the working name."""
    scene = make_scene(tmp_path / "photos", n=3, size_wh=(64, 48))
    write_image(scene / "view_001.JPG", read_image(scene / "view_001.png"))
    (scene / "view_001.png").unlink()
    _turn(scene / "view_002.png")
    out = tmp_path / "out"
    run_pipeline(scene, out, PipelineConfig(views=3, rounds=1), stages=TinyStages().stages())
    working = read_sparse_model(out / "round1" / "sparse" / "0")
    assert sorted(working.names) == ["view_000.png", "view_001.png", "view_002.png"]
    sizes = read_sizes(out / WORKING_DIR / SIZES_FILE)
    full = input_size_cameras(working, sizes)
    assert sorted(full.names) == ["view_000.png", "view_001.JPG", "view_002.png"]
    assert (full.camera_of("view_002.png").width, full.camera_of("view_002.png").height) == (48, 64)
    np.testing.assert_array_equal(full.image("view_001.JPG").cam_from_world,
                                  working.image("view_001.png").cam_from_world)
    older = {stem: {k: v for k, v in entry.items() if k != "file"} for stem, entry in sizes.items()}
    assert sorted(input_size_cameras(working, older).names) == sorted(working.names)
    raw = json.loads((out / WORKING_DIR / SIZES_FILE).read_text())
    raw["view_000"]["file"] = "../view_000.png"
    (out / WORKING_DIR / SIZES_FILE).write_text(json.dumps(raw))
    with pytest.raises(InputError, match="file must be the name of its photo"):
        read_sizes(out / WORKING_DIR / SIZES_FILE)


def test_an_evaluation_image_of_another_size_than_its_camera_is_refused(tmp_path):
    """A clean or noisy image whose size is not its camera's is named before any method runs (it failed after
    the training, or only as a failed run)."""
    from eval.pipeline import validate_dataset_folder
    from mvgeo.camera import Camera
    from mvgeo.sparse_model import PosedImage, SparseModel, write_sparse_model

    root = tmp_path / "ds"
    make_scene(root / "images", n=4, size_wh=(64, 48))
    make_scene(root / "clean", n=4, size_wh=(64, 48))
    images = [PosedImage(f"view_00{i}.png", 1, np.hstack([np.eye(3), [[0.0], [0.0], [float(i)]]])) for i in range(4)]
    write_sparse_model(root / "sparse" / "0", SparseModel({1: Camera.pinhole(50.0, 50.0, 32.0, 24.0, 64, 48)}, images,
                                                          np.zeros((0, 3)), np.zeros((0, 3), np.uint8)), binary=False)
    (root / "split.json").write_text(json.dumps({"train": [f"view_00{i}.png" for i in range(3)],
                                                 "test": ["view_003.png"]}))
    assert validate_dataset_folder(root).test == ["view_003"]
    write_image(root / "clean" / "view_003.png", np.zeros((20, 20, 3), np.float32))
    with pytest.raises(InputError, match=r"20x20 but its camera in sparse/0 is 64x48") as err:
        validate_dataset_folder(root)
    assert err.value.path == root / "clean" / "view_003.png"
    write_image(root / "clean" / "view_003.png", np.zeros((48, 64, 3), np.float32))
    write_image(root / "clean" / "view_000.png", np.zeros((20, 20, 3), np.float32))  # oracle_clean splats it
    with pytest.raises(InputError, match=r"20x20 but its camera in sparse/0 is 64x48"):
        validate_dataset_folder(root)
    write_image(root / "clean" / "view_000.png", np.zeros((48, 64, 3), np.float32))
    write_image(root / "images" / "view_001.png", np.zeros((30, 40, 3), np.float32))
    with pytest.raises(InputError, match=r"40x30 but its camera in sparse/0 is 64x48"):
        validate_dataset_folder(root)
