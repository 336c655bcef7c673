"""`denoise-gs` command line: input errors exit 2 before any compute, with a clear message."""

from __future__ import annotations

import dataclasses
import json
import shutil

import cv2
import numpy as np
import pytest

import eval.cli
from eval.cli import main
from eval.pipeline import preset, validate_run_inputs
from mvgeo.common.errors import InputError
from tests.common.cli_contract import assert_refused
from tests.eval._tiny_stages import make_scene, tiny_dataset


def _err(capsys) -> str:
    return capsys.readouterr().err


def test_run_missing_folder(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope"), "--out", str(tmp_path / "out")]) == 2
    err = _err(capsys)
    assert "nope" in err and "does not exist" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_run_fewer_images_than_views(tmp_path, capsys):
    scene = make_scene(tmp_path / "images", n=4)
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--views", "6", "--preset", "fast",
                 "--rounds", "2"]) == 2
    err = _err(capsys)
    assert "4 images but --views 6" in err and "--views 4" in err
    assert not (tmp_path / "out").exists()


def test_run_bad_values(tmp_path, capsys):
    scene = make_scene(tmp_path / "images", n=4)
    for option, value in (("--views", "1"), ("--rounds", "0")):  # checked by the parser: usage error, exit 2
        with pytest.raises(SystemExit) as exc:
            main(["run", str(scene), "--out", str(tmp_path / "out"), option, value])
        assert exc.value.code == 2 and f"argument {option}" in _err(capsys)
    with pytest.raises(SystemExit) as exc:
        main(["run", str(scene), "--out", str(tmp_path / "out"), "--preset", "turbo"])
    assert exc.value.code == 2
    (tmp_path / "file").write_text("x")
    assert main(["run", str(scene), "--out", str(tmp_path / "file"), "--views", "4"]) == 2
    assert "not a folder" in _err(capsys)


@pytest.mark.parametrize(("flag", "expected"), [
    ([], ("auto", False)),  # the default preset (one round of a non-blind denoiser) does not fuse
    (["--fuse-noisy-splat"], ("auto", True)),
    (["--reuse-intrinsics", "never"], ("never", False)),
    (["--no-fuse-noisy-splat"], ("auto", False)),
    (["--preset", "fast"], ("auto", False)),  # `fast` takes the noisy band instead
    (["--preset", "fast", "--fuse-noisy-splat"], ("auto", True)),
    (["--preset", "fast", "--align-photos", "noisy_first"], ("auto", False)),
])
def test_run_pipeline_flags(tmp_path, monkeypatch, flag, expected):

    seen = {}

    def fake_run(images_dir, out, config, force=False):  # stands in for the hours of compute
        seen["config"] = config
        raise SystemExit(0)

    monkeypatch.setattr(eval.cli, "run_pipeline", fake_run)
    with pytest.raises(SystemExit):
        main(["run", str(make_scene(tmp_path / "images", n=4)), "--out", str(tmp_path / "out"), "--views", "4",
              *flag])
    assert (seen["config"].align.reuse_intrinsics, seen["config"].fuse_noisy_splat) == expected
    expected_photos = ("noisy_first" if "noisy_first" in flag else "denoised" if "fast" in flag else "better_of")
    assert seen["config"].align.photos == expected_photos


@pytest.mark.parametrize(("flag", "expected"), [
    ([], True), (["--no-wiener"], False), (["--preset", "fast"], True), (["--preset", "fast", "--no-wiener"], False),
])
def test_run_wiener_flag(tmp_path, monkeypatch, flag, expected):
    seen = {}

    def fake_run(images_dir, out, config, force=False):
        seen["config"] = config
        raise SystemExit(0)

    monkeypatch.setattr(eval.cli, "run_pipeline", fake_run)
    with pytest.raises(SystemExit):
        main(["run", str(make_scene(tmp_path / "images", n=4)), "--out", str(tmp_path / "out"), "--views", "4",
              *flag])
    assert seen["config"].denoise.wiener is expected


@pytest.mark.parametrize("preset_name", ["default", "best", "fast"])
def test_run_two_rounds_with_the_n2v_denoiser_from_any_preset(tmp_path, monkeypatch, capsys, preset_name):
    """The paper's loop (`--denoiser n2v --rounds 2`) runs from every preset: the rounds are checked against the
    denoiser given, not the preset's; a denoiser that cannot run a round 2 is refused, naming both fixes."""
    seen = {}

    def fake_run(images_dir, out, config, force=False):
        seen["config"] = config
        raise SystemExit(0)

    monkeypatch.setattr(eval.cli, "run_pipeline", fake_run)
    scene = make_scene(tmp_path / "images", n=4)
    with pytest.raises(SystemExit):
        main(["run", str(scene), "--out", str(tmp_path / "out"), "--views", "4", "--preset", preset_name,
              "--denoiser", "n2v", "--rounds", "2"])
    assert (seen["config"].denoise.method, seen["config"].rounds) == ("n2v", 2)
    if preset_name == "fast":
        return
    seen.clear()
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--views", "4", "--preset", preset_name,
                 "--rounds", "2"]) == 2
    err = capsys.readouterr().err
    assert "round 1 only" in err and "--denoiser n2v" in err and "--preset fast" in err and not seen


def test_run_corrupt_image(tmp_path, capsys):
    scene = make_scene(tmp_path / "images", n=4)
    (scene / "view_002.png").write_bytes(b"\x89PNG broken")
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--views", "4"]) == 2
    assert "view_002.png" in _err(capsys)


def test_run_refuses_mixed_image_sizes_before_any_output(tmp_path, capsys):
    """Images of different sizes stop the run up front, naming two files and their sizes (the alignment
    used to refuse them after the denoise stage had written OUT/inputs and round1/)."""
    from mvgeo.common.imageio import read_image, write_image

    scene = make_scene(tmp_path / "images", n=6, size_wh=(64, 48))
    big = scene / "view_003.png"
    write_image(big, cv2.resize(read_image(big), (160, 120)))
    err = assert_refused(main, ["run", scene, "--out", tmp_path / "out", "--views", "6"], capsys, inputs=[scene],
                         watch=[tmp_path], message=["view_000.png: 64x48", "view_003.png: 160x120",
                                                    "resize or crop all images to one size"])
    assert str(scene) in err


def test_run_with_a_calibration_refuses_a_portrait_photo_among_landscape_ones(tmp_path, capsys):
    """A photo turned by 90 degrees is turned back by the run (tests/eval/test_turned_photos.py), except
    with --intrinsics (one calibration of one input size): the fix says to rotate it, not to resize it."""
    from mvgeo.common.imageio import read_image, write_image

    scene = make_scene(tmp_path / "images", n=4, size_wh=(64, 48))
    turned = scene / "view_002.png"
    write_image(turned, np.ascontiguousarray(np.rot90(read_image(turned))))
    cams = tmp_path / "cameras.txt"
    cams.write_text("1 PINHOLE 64 48 60 60 32 24\n")
    assert_refused(main, ["run", scene, "--out", tmp_path / "out", "--views", "4", "--intrinsics", cams], capsys,
                   inputs=[scene, cams], watch=[tmp_path],
                   message=["view_000.png: 64x48", "view_002.png: 48x64", "portrait",
                            "rotate the photos to the calibration's orientation first, without resizing"])


def test_run_sizes_are_compared_at_the_working_size(tmp_path):
    """Inputs that --max-size brings to one working size are accepted (each keeps its input-size camera);
    the same inputs without downscaling, or ones of another shape, are refused naming the working sizes."""
    from mvgeo.common.imageio import read_image, write_image

    scene = make_scene(tmp_path / "images", n=3, size_wh=(96, 64))
    write_image(scene / "view_001.png", cv2.resize(read_image(scene / "view_001.png"), (192, 128)))
    cfg = preset("fast", views=3)
    assert list(validate_run_inputs(scene, dataclasses.replace(cfg, max_size=96))) == [
        "view_000", "view_001", "view_002"]
    with pytest.raises(InputError, match="view_000.png: 96x64, view_001.png: 192x128"):
        validate_run_inputs(scene, dataclasses.replace(cfg, max_size=None))
    write_image(scene / "view_002.png", cv2.resize(read_image(scene / "view_002.png"), (128, 128)))
    with pytest.raises(InputError, match="at --max-size 96 they are 96x64 and 96x96"):
        validate_run_inputs(scene, dataclasses.replace(cfg, max_size=96))


def test_run_refuses_a_copy_of_a_photo_up_front(tmp_path, capsys):
    """A photo twice under two names carries no geometry. The alignment refuses identical images, but in
    the run it sees the denoised photos, which the denoiser makes differ: the copy went on as a view of
    its own. Refused before any work, naming the two photos."""
    scene = make_scene(tmp_path / "images", n=4, size_wh=(64, 48))
    shutil.copy(scene / "view_002.png", scene / "view_002(1).png")
    cfg = preset("fast", views=3)
    with pytest.raises(InputError, match=r"'view_002.png' and 'view_002\(1\).png' hold the same pixels"):
        validate_run_inputs(scene, cfg)
    assert_refused(main, ["run", scene, "--out", tmp_path / "out", "--views", "3"], capsys,
                   inputs=[scene], watch=[tmp_path], message=["view_002.png", "remove one of them"])
    (scene / "view_002(1).png").unlink()
    assert list(validate_run_inputs(scene, cfg)) == ["view_000", "view_001", "view_002", "view_003"]


def test_run_refuses_file_names_with_spaces_up_front(tmp_path, capsys):
    """The run writes its cameras as COLMAP text models, whose images.txt cannot hold a name with a space
    (COLMAP and pycolmap read 'view 1.png' back as 'view'): refused before any work, naming the file."""
    scene = make_scene(tmp_path / "images", n=4, size_wh=(64, 48))
    (scene / "view_001.png").rename(scene / "view 1.png")
    with pytest.raises(InputError, match=r"the file name 'view 1.png' holds white space"):
        validate_run_inputs(scene, preset("fast", views=3))
    assert_refused(main, ["run", scene, "--out", tmp_path / "out", "--views", "3"], capsys,
                   inputs=[scene], watch=[tmp_path], message=["view 1.png", "without spaces"])


def _dataset(tmp_path):
    root = tmp_path / "ds"
    make_scene(root / "images", n=4)
    shutil.copytree(root / "images", root / "clean")
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "split.json").write_text(json.dumps({"train": ["view_001", "view_002", "view_003"],
                                                 "test": ["view_000"]}))
    return root


@pytest.mark.parametrize(("remove", "message"), [("clean", "clean/"), ("split.json", "split.json"),
                                                  ("sparse", "sparse/0")])
def test_eval_dataset_missing_parts(tmp_path, capsys, remove, message):
    root = _dataset(tmp_path)
    target = root / remove
    shutil.rmtree(target) if target.is_dir() else target.unlink()
    assert main(["eval", str(root), "--out", str(tmp_path / "out")]) == 2
    assert message in _err(capsys)


@pytest.mark.parametrize(("content", "message"), [
    (b'{"train": ["view_001", "caf\xe9"], "test": ["view_000"]}', "not UTF-8 text"),
    (b'{"train": 5, "test": ["view_000"]}', "'train' must be a list of image names"),
    (b'{"train": ["view_001"], "test": "view_000"}', "'test' must be a list of image names"),
    (b'{"train": ["view_001", 2], "test": ["view_000"]}', "'train' must be a list of image names"),
    (b'[["view_001"], ["view_000"]]', "not an object"),
    (b'{"train": [', "split.json is not valid JSON"),
])
def test_eval_refuses_a_malformed_split_json(tmp_path, capsys, content, message):
    root = _dataset(tmp_path)
    (root / "split.json").write_bytes(content)
    assert_refused(main, ["eval", root, "--out", tmp_path / "out"], capsys, inputs=[root], watch=[tmp_path],
                   message=[str(root / "split.json"), message, "fix:"])


@pytest.mark.parametrize(("model", "params", "message"), [
    ("OPENCV", [50.0, 50.0, 24.0, 20.0, 0.1, 0.0, 0.0, 0.0], "lens distortion"),
    ("PINHOLE", [0.0, 50.0, 24.0, 20.0], "focal length is not positive"),
])
def test_eval_refuses_true_cameras_the_splat_cannot_render_before_any_compute(tmp_path, capsys, monkeypatch, model,
                                                                             params, message):
    """The methods that splat with the true cameras (3dgs_gt_poses, the @gt_poses variants) would fail after
    their training on a distorted camera or a focal of 0: refused up front, naming sparse/0. Methods that
    render with their own cameras still run on such a dataset."""
    from mvgeo.camera import Camera
    from mvgeo.sparse_model import SparseModel, read_sparse_model, write_sparse_model

    root = tiny_dataset(tmp_path / "data").root
    shutil.copytree(root / "images", root / "clean")
    sparse = root / "sparse" / "0"
    good = read_sparse_model(sparse)
    cam = good.cameras[1]
    write_sparse_model(sparse, SparseModel({1: Camera(model, cam.width, cam.height, params)}, good.images,
                                           good.points_xyz, good.points_rgb), binary=True)
    for methods in (["3dgs_gt_poses"], ["instantsplat", "product@gt_poses"]):
        assert_refused(main, ["eval", root, "--out", tmp_path / "out", "--methods", *methods], capsys,
                       inputs=[root], watch=[tmp_path], message=[str(sparse), "camera 1", message, "fix:"])
    from eval.results import RunScores

    seen = []
    monkeypatch.setattr(eval.cli, "evaluate_dataset", lambda dataset, out, config, *, scene, **kw: seen.append(
        config.methods) or [RunScores(scene, m, 0, 25.0, 0.8, 0.1) for m in config.methods])
    assert main(["eval", str(root), "--out", str(tmp_path / "own"), "--methods", "instantsplat"]) == 0
    assert seen == [("instantsplat",)]


def test_eval_split_and_methods(tmp_path, capsys):
    root = _dataset(tmp_path)
    (root / "split.json").write_text(json.dumps({"train": ["view_001"], "test": ["view_009"]}))
    assert main(["eval", str(root), "--out", str(tmp_path / "out")]) == 2
    assert "view_009" in _err(capsys)
    root = _dataset(tmp_path / "b")
    assert main(["eval", str(root), "--out", str(tmp_path / "out"), "--methods", "magic"]) == 2
    assert "magic" in _err(capsys)
    assert main(["eval", "no_such_scene", "--out", str(tmp_path / "out")]) == 2
    assert "built-in scenes" in _err(capsys)
    assert main(["eval", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "out")]) == 2


def test_eval_refuses_a_held_out_view_without_its_noisy_photo_before_any_output(tmp_path, capsys):
    """The pose-free methods fit each held-out camera to the noisy held-out photo before scoring against the
    clean one: a dataset without it ended every such run in a KeyError after its training."""
    root = _dataset(tmp_path)
    (root / "images" / "view_000.png").unlink()
    assert_refused(main, ["eval", root, "--out", tmp_path / "out"], capsys, inputs=[root], watch=[tmp_path],
                   message=[str(root / "images"), "held-out view 'view_000' has no noisy image", "fix:"])


def test_eval_dataset_without_cameras(tmp_path, capsys):
    root = _dataset(tmp_path)  # sparse/0 exists but holds no COLMAP files
    assert main(["eval", str(root), "--out", str(tmp_path / "out"), "--methods", "3dgs_gt_poses"]) == 2
    assert "COLMAP" in _err(capsys)


def test_cost_rejects_a_bad_dataset_before_compute(tmp_path, capsys):
    root = _dataset(tmp_path)
    (root / "split.json").unlink()
    assert main(["cost", str(root), "--out", str(tmp_path / "out")]) == 2
    assert "split.json" in _err(capsys)


@pytest.mark.slow  # renders a 128x96 llff_like and trains a splat (60 iters)
def test_eval_gt_poses_end_to_end(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["eval", "llff_like", "--out", str(out), "--methods", "3dgs_gt_poses", "--seeds", "1",
                 "--splat-iters", "60", "--size", "128x96", "--scene-views", "8"])
    assert code == 0, _err(capsys)
    data = json.loads((out / "results.json").read_text())
    run = data["runs"][0]
    assert run["method"] == "3dgs_gt_poses" and run["per_view"]
    # A 60-iteration splat of a noisy scene: far from perfect but clearly an image of the scene.
    assert 10.0 < run["psnr_db"] < 40.0 and 0.0 < run["lpips"] < 1.0
    assert (out / "results.md").read_text().count("3dgs_gt_poses") >= 1
    # held-out renders kept and shown next to the clean and noisy views
    assert sorted(p.name for p in (out / "heldout" / "llff_like").iterdir()) == ["3dgs_gt_poses", "_clean", "_noisy"]
    assert (out / "figures" / "heldout_llff_like.png").is_file()


def test_gt_pose_variants_add_one_row_per_method_with_estimated_poses(tmp_path, monkeypatch):
    import eval.evaluate

    seen = {}

    def record(dataset, out, config, **kw):
        seen["methods"] = config.methods
        return []

    monkeypatch.setattr(eval.cli, "evaluate_dataset", record)
    root = tiny_dataset(tmp_path / "data").root
    shutil.copytree(root / "images", root / "clean")
    code = main(["eval", str(root), "--out", str(tmp_path / "out"), "--seeds", "1", "--gt-pose-variants",
                 "--methods", "3dgs_gt_poses", "instantsplat", "n2v_fused_round1"])
    assert code == 0
    assert seen["methods"] == ("3dgs_gt_poses", "instantsplat", "n2v_fused_round1", "instantsplat@gt_poses",
                               "n2v_fused_round1@gt_poses")
    assert [m.name for m in eval.evaluate.EvalConfig(methods=seen["methods"]).selected()][-2:] == [
        "instantsplat@gt_poses", "n2v_fused_round1@gt_poses"]


def test_eval_whose_every_run_failed_exits_1_with_the_reason(tmp_path, monkeypatch, capsys):
    """The table is written either way; where no run of the invocation succeeded the command says so and exits
    1; one run that succeeded is a result (a refusal of another method is a finding, exit 0)."""
    from eval.results import RunScores

    nan = float("nan")
    outcome = {}

    def fake(dataset, out, config, *, scene, **kw):
        return [RunScores(scene, m, s, *((25.0, 0.8, 0.1) if outcome.get(m) else (nan, nan, nan)),
                          error="" if outcome.get(m) else "needs initial points: no depth/ maps")
                for m in config.methods for s in config.seed_values]

    monkeypatch.setattr(eval.cli, "evaluate_dataset", fake)
    root = tiny_dataset(tmp_path / "data").root
    shutil.copytree(root / "images", root / "clean")
    args = ["eval", str(root), "--seeds", "2", "--methods", "instantsplat", "3dgs_gt_poses"]
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "a")]) == 1
    err = capsys.readouterr().err
    assert "every run of this evaluation failed (4)" in err and "needs initial points" in err
    assert (tmp_path / "a" / "results.md").is_file() and "Traceback" not in err
    outcome["instantsplat"] = True
    assert main([*args, "--out", str(tmp_path / "b")]) == 0


def test_eval_into_the_same_folder_extends_its_table_with_the_same_settings(tmp_path, monkeypatch, capsys):
    """One method now, another later into the same --out: one table with both; other settings replace it."""
    from eval.results import RunScores

    def fake(dataset, out, config, *, scene, **kw):
        psnr = {"instantsplat": 22.0, "product": 25.0}
        return [RunScores(scene, m, s, psnr[m] + s, 0.5, 0.2) for m in config.methods for s in config.seed_values]

    monkeypatch.setattr(eval.cli, "evaluate_dataset", fake)
    root = tiny_dataset(tmp_path / "data").root
    shutil.copytree(root / "images", root / "clean")
    out = tmp_path / "out"

    def runs():
        return [(r["method"], r["seed"], r["psnr_db"]) for r in json.loads((out / "results.json").read_text())["runs"]]

    assert main(["eval", str(root), "--out", str(out), "--seeds", "2", "--methods", "instantsplat"]) == 0
    assert main(["eval", str(root), "--out", str(out), "--seeds", "1", "--methods", "product"]) == 0
    assert runs() == [("instantsplat", 0, 22.0), ("instantsplat", 1, 23.0), ("product", 0, 25.0)]
    md = (out / "results.md").read_text()
    assert "| instantsplat |" in md and "| product |" in md
    # The same run again replaces its row, not adds one.
    assert main(["eval", str(root), "--out", str(out), "--seeds", "1", "--methods", "instantsplat"]) == 0
    assert runs() == [("instantsplat", 1, 23.0), ("product", 0, 25.0), ("instantsplat", 0, 22.0)]
    # Another preset: the earlier rows are not comparable, so the table is this invocation's alone, with a warning.
    capsys.readouterr()
    assert main(["eval", str(root), "--out", str(out), "--seeds", "1", "--methods", "product",
                 "--preset", "fast"]) == 0
    assert runs() == [("product", 0, 25.0)]
    assert "settings differ: preset" in capsys.readouterr().err


def test_eval_seed_by_seed_into_one_folder(tmp_path, monkeypatch):
    """`--first-seed K`: an evaluation run in parts, each part its own seeds, adds up to one table."""
    from eval.results import RunScores

    asked = []

    def fake(dataset, out, config, *, scene, **kw):
        asked.append(list(config.seed_values))
        return [RunScores(scene, m, s, 20.0 + s, 0.5, 0.2) for m in config.methods for s in config.seed_values]

    monkeypatch.setattr(eval.cli, "evaluate_dataset", fake)
    root = tiny_dataset(tmp_path / "data").root
    shutil.copytree(root / "images", root / "clean")
    out = tmp_path / "out"
    assert main(["eval", str(root), "--out", str(out), "--seeds", "1", "--methods", "product"]) == 0
    assert main(["eval", str(root), "--out", str(out), "--first-seed", "1", "--seeds", "2",
                 "--methods", "product"]) == 0
    assert asked == [[0], [1, 2]]
    rows = json.loads((out / "results.json").read_text())["runs"]
    assert sorted((r["seed"], r["psnr_db"]) for r in rows) == [(0, 20.0), (1, 21.0), (2, 22.0)]
    md = (out / "results.md").read_text()
    assert "(3 seed(s))" in md and "| product | 21.00 ± 1.00 |" in md  # the mean over seeds 0-2


def test_eval_first_seed_must_be_a_seed(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["eval", "llff_like", "--out", str(tmp_path / "o"), "--first-seed", "-1"])
    assert exc.value.code == 2 and "--first-seed" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["disconnected", "refused"])
def test_cost_on_a_rendered_scene_names_the_render_options_in_a_refusal(tmp_path, capsys, monkeypatch, kind):
    """An alignment refusal in a sweep over a scene the command renders: the pipeline's fix speaks of an input
    folder the user does not have; `denoise-gs cost` names --size and --scene-views instead (exit 2 for views
    that no pair relates, an input problem; 1 for a refused result, as every command exits on one)."""
    import eval.cost
    from eval.pipeline.align_stage import as_pipeline_refusal
    from mvgeo.common.errors import AlignmentRefusedError, DisconnectedViewsError

    def refused(*args, **kwargs):
        exc = (DisconnectedViewsError("the pair graph is disconnected", views=["view_003.png"])
               if kind == "disconnected" else
               AlignmentRefusedError("1 of 4 views rest on a single pair", kind="views_unsupported",
                                     views=["view_003.png"]))
        raise as_pipeline_refusal(exc)

    monkeypatch.setattr(eval.cost, "run_cost_sweep", refused)
    code = main(["cost", "llff_like", "--out", str(tmp_path / "out"), "--size", "64x48", "--scene-views", "4"])
    err = _err(capsys)
    assert code == (2 if kind == "disconnected" else 1)
    assert "--size" in err and "--scene-views" in err and "64x48" in err
    assert "input folder" not in err and "Traceback" not in err
