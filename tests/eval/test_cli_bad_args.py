"""`denoise-gs run|eval|cost` check `--device` and every numeric option before any stage runs: exit 2,
no traceback, inputs byte-identical, no output folder or temporary left; the pipeline's N2V stage
trains on the configured device."""

import time

import pytest
import torch

from eval.cli import main
from tests.common.cli_contract import assert_refused
from tests.eval._tiny_stages import make_scene


@pytest.fixture
def no_work(monkeypatch):
    """Any stage, scene render or sweep means the checks came too late."""
    import eval.cli
    import eval.methods

    def fail(*args, **kwargs):
        raise AssertionError("work started before the options were checked")

    monkeypatch.setattr(eval.cli, "run_pipeline", fail)
    monkeypatch.setattr(eval.cli, "scene_dataset", fail)
    monkeypatch.setattr(eval.methods, "run_pipeline", fail)


@pytest.fixture
def images(tmp_path):
    return make_scene(tmp_path / "images", n=4)


@pytest.mark.parametrize(("device", "message"), [("cuda", "CUDA is not available"), ("cuda:0", "CUDA is not available"),
                                                 ("cudaa", "unknown device"), ("banana", "unknown device")])
def test_run_device_is_checked_before_any_stage(images, tmp_path, capsys, no_cuda, no_work, device, message):
    start = time.perf_counter()
    assert_refused(main, ["run", images, "--out", tmp_path / "O", "--preset", "fast", "--views", "4",
                          "--device", device], capsys, inputs=[images], watch=[tmp_path], message=["--device", message])
    assert time.perf_counter() - start < 5.0


@pytest.mark.parametrize("command", ["eval", "cost"])
def test_eval_and_cost_device(images, tmp_path, capsys, no_cuda, no_work, command):
    assert_refused(main, [command, "llff_like", "--out", tmp_path / "O", "--device", "cuda"], capsys,
                   inputs=[images], watch=[tmp_path], message="CUDA is not available")
    assert_refused(main, [command, "llff_like", "--out", tmp_path / "O", "--device", "cudaa"], capsys,
                   inputs=[images], watch=[tmp_path], message="unknown device")


def test_cuda_index_beyond_the_gpus(images, tmp_path, capsys, monkeypatch, no_work):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert_refused(main, ["run", images, "--out", tmp_path / "O", "--views", "4", "--device", "cuda:3"], capsys,
                   inputs=[images], watch=[tmp_path], message="1 CUDA device")


@pytest.mark.parametrize("argv", [
    ["run", "IMAGES", "--views", "0"], ["run", "IMAGES", "--views", "1"], ["run", "IMAGES", "--rounds", "0"],
    ["run", "IMAGES", "--seed", "-1"], ["run", "IMAGES", "--views", "two"],
    ["eval", "llff_like", "--seeds", "0"], ["eval", "llff_like", "--splat-iters", "-1"],
    ["eval", "llff_like", "--splat-iters", "0"], ["eval", "llff_like", "--pose-fit-iters", "-1"],
    ["eval", "llff_like", "--views", "1"], ["eval", "llff_like", "--scene-views", "0"],
    ["eval", "llff_like", "--size", "0x5"], ["eval", "llff_like", "--size", "16x16"],
    ["cost", "llff_like", "--rounds", "0"], ["cost", "llff_like", "--views", "1"],
    ["cost", "llff_like", "--scene-views", "1"], ["cost", "llff_like", "--seed", "-3"],
    ["cost", "llff_like", "--pose-fit-iters", "-1"], ["cost", "llff_like", "--size", "64x0"],
])
def test_numeric_options_are_checked_by_the_parser(images, tmp_path, capsys, no_work, argv):
    argv = [images if a == "IMAGES" else a for a in argv]
    option = next(a for a in argv if str(a).startswith("--"))
    assert_refused(main, [*argv[:2], "--out", tmp_path / "O", *argv[2:]], capsys, inputs=[images],
                   watch=[tmp_path], message=f"argument {option}")


def test_the_denoise_stage_trains_on_the_configured_device(tmp_path, monkeypatch):
    """The round-1 training receives the pipeline's device (it used to train on the CPU always)."""
    import denoise.self_supervised
    from eval.pipeline import DenoiseSettings, stages
    from eval.pipeline.stage import StageContext
    from eval.pipeline.stage_settings import DenoiseStageSettings, n2v_config

    class Stop(Exception):
        pass

    seen = []

    def recording(images, config, *, seed, device, noise_sigma=None, noise_model="auto"):
        seen.append(device)
        raise Stop

    # The stage trains through `train_with_method` (any `DenoiseSettings.method`), imported when it runs.
    monkeypatch.setattr(denoise.self_supervised, "train_with_method", recording)
    images = make_scene(tmp_path / "noisy", n=2)
    settings = DenoiseStageSettings(n2v_config(DenoiseSettings(n2v_preset="fast", n2v_steps=2)), passes=1,
                                    device="cuda:1")
    ctx = StageContext(name="denoise", work_dir=tmp_path / "w", inputs={"noisy": images}, settings=settings, seed=0)
    with pytest.raises(Stop):
        stages.denoise(ctx)
    assert seen == ["cuda:1"]


@pytest.mark.parametrize(("argv", "message"), [
    (["eval", "llff_like", "--size", "64x48", "--scene-views", "2", "--methods", "3dgs_gt_poses"],
     ["needs at least 2 training views", "the scene rendered with 2 views has 1", "--scene-views"]),
    (["eval", "llff_like", "--size", "64x48", "--scene-views", "4", "--views", "5", "--methods", "denoise_gs"],
     ["--views 5", "3 training views", "--views of 2..3"]),
    (["cost", "llff_like", "--size", "64x48", "--scene-views", "2"], ["the cost sweep needs at least 2 training"]),
    (["cost", "llff_like", "--size", "64x48", "--scene-views", "4", "--grid", "train_views=9", "--knobs",
      "train_views"], ["train_views=9", "(3)"]),
])
def test_too_few_training_views_of_a_rendered_scene_are_refused_before_it_is_rendered(tmp_path, capsys, no_work, argv,
                                                                                    message):
    assert_refused(main, [*argv, "--out", tmp_path / "O"], capsys, inputs=[], watch=[tmp_path], message=message)


def test_eval_views_above_a_datasets_training_views_is_refused_before_any_output(tmp_path, capsys, no_work):
    import json
    import shutil

    root = tmp_path / "ds"
    make_scene(root / "images", n=4)
    shutil.copytree(root / "images", root / "clean")
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "split.json").write_text(json.dumps({"train": ["view_001", "view_002", "view_003"], "test": ["view_000"]}))
    assert_refused(main, ["eval", root, "--out", tmp_path / "O", "--methods", "denoise_gs", "--views", "5"], capsys,
                   inputs=[root], watch=[tmp_path], message=["--views 5", "split.json", "3 training views"])
