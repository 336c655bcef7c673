"""`denoise n2v|select` refuse bad numeric options, devices and images before any work (exit 2, no
traceback, inputs byte-identical, nothing left behind); N2V trains and infers on `--device`."""

import numpy as np
import pytest
import torch

import denoise.cli
from denoise.cli import main
from denoise.inference import denoise_images
from denoise.model import N2VModel
from denoise.n2v import n2v_preset, train_n2v
from denoise.round2 import Round2Config, refine_round2
from denoise.self_supervised import train_with_method
from mvgeo.common.imageio import write_image
from tests.common.cli_contract import assert_refused
from tests.denoise._synth import add_noise, smooth_scene


@pytest.fixture
def noisy(tmp_path, rng):
    src = tmp_path / "noisy"
    src.mkdir()
    for name in ("a.png", "b.png"):
        write_image(src / name, add_noise(rng, smooth_scene(rng, 32, 40), 0.1))
    return src


@pytest.fixture
def no_training(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("training started before the options were checked")

    monkeypatch.setattr(denoise.cli, "train_with_method", fail)


@pytest.mark.parametrize(("option", "value"), [("--steps", "0"), ("--steps", "-3"), ("--passes", "-1"),
                                               ("--seed", "-1"), ("--steps", "1.5")])
def test_n2v_numeric_options(noisy, tmp_path, capsys, no_training, option, value):
    assert_refused(main, ["n2v", noisy, "--out", tmp_path / "out", option, value], capsys, inputs=[noisy],
                   watch=[tmp_path], message=f"argument {option}")


@pytest.mark.parametrize(("device", "message"), [("cudaa", "unknown device"), ("banana", "unknown device"),
                                                 ("cuda", "CUDA is not available")])
def test_n2v_device_is_checked_first(noisy, tmp_path, capsys, monkeypatch, no_training, device, message):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert_refused(main, ["n2v", noisy, "--out", tmp_path / "out", "--device", device], capsys, inputs=[noisy],
                   watch=[tmp_path], message=["--device", message])


def test_n2v_one_pixel_image_is_named(noisy, tmp_path, capsys, no_training):
    write_image(noisy / "c_tiny.png", np.full((1, 1, 3), 0.5, np.float32))
    assert_refused(main, ["n2v", noisy, "--out", tmp_path / "out", "--steps", "2"], capsys, inputs=[noisy],
                   watch=[tmp_path], message=[str(noisy / "c_tiny.png"), "1x1 px", "fix:"])


def test_select_k_must_be_positive(noisy, tmp_path, capsys):
    sparse = tmp_path / "sparse"
    sparse.mkdir()
    assert_refused(main, ["select", sparse, "--images", noisy, "--k", "0"], capsys, inputs=[noisy, sparse],
                   watch=[tmp_path], message="argument --k")


def test_n2v_cli_trains_on_the_given_device(noisy, tmp_path, monkeypatch):
    """`--device` reaches the training (it used to be ignored)."""
    seen = []

    def recording(images, config, *, seed, device, noise_model):
        seen.append(torch.device(device))
        return train_with_method(images, config, seed=seed, device=device, noise_model=noise_model)

    monkeypatch.setattr(denoise.cli, "train_with_method", recording)
    assert main(["n2v", str(noisy), "--out", str(tmp_path / "out"), "--steps", "2", "--passes", "1",
                 "--preset", "fast", "--device", "cpu"]) == 0
    assert seen == [torch.device("cpu")]


def _images(rng, n=2):
    return [add_noise(rng, smooth_scene(rng, 32, 40), 0.1) for _ in range(n)]


def test_train_n2v_device_cpu_is_the_default_bit_for_bit(rng):
    images = _images(rng)
    cfg = n2v_preset("fast", steps=3, batch_size=2, patch_px=16)
    a = train_n2v(images, cfg, seed=4)
    b = train_n2v(images, cfg, seed=4, device="cpu")
    assert a.history == b.history
    for pa, pb in zip(a.unet.parameters(), b.unet.parameters(), strict=True):
        assert torch.equal(pa, pb)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_n2v_and_round2_run_on_cuda(rng):
    """Training, inference and the round-2 fine-tuning stay on the GPU and agree with the CPU."""
    images = _images(rng)
    cfg = n2v_preset("fast", steps=20, batch_size=4, patch_px=16)
    gpu = train_n2v(images, cfg, seed=1, device="cuda")
    cpu = train_n2v(images, cfg, seed=1, device="cpu")
    assert all(p.device.type == "cuda" for p in gpu.unet.parameters())
    # Same patches (numpy), different mask random streams (CUDA vs CPU generator): losses agree in scale.
    assert np.isfinite(gpu.history).all() and 0.2 < np.mean(gpu.history) / np.mean(cpu.history) < 5
    out = denoise_images(gpu, images, passes=2, seed=0)
    assert all(o.shape == im.shape and np.isfinite(o).all() for o, im in zip(out, images, strict=True))
    tuned, report = refine_round2(gpu, images, out, Round2Config(steps=5, batch_size=2, patch_px=16), seed=0)
    assert isinstance(tuned, N2VModel) and np.isfinite(report.loss_after)
    assert all(p.device.type == "cuda" for p in tuned.unet.parameters())


def test_n2v_images_sharing_a_stem_are_refused(noisy, tmp_path, capsys, no_training, rng):
    """`a.png` and `a.jpg` would both be written as `a.png`: one result would silently replace the other."""
    write_image(noisy / "a.jpg", add_noise(rng, smooth_scene(rng, 32, 40), 0.1))
    assert_refused(main, ["n2v", noisy, "--out", tmp_path / "out", "--steps", "2"], capsys, inputs=[noisy],
                   watch=[tmp_path], message=["two images share the name 'a'", "a.jpg", "a.png", "fix:"])
