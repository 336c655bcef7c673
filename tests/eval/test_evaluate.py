"""Evaluation plumbing that runs without the full pipeline: method settings and the classical stages."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from eval.evaluate import (
    EVAL_METHODS,
    EvalConfig,
    _identity_stage,
    _nlm_stage,
    _oracle_clean_stage,
    method_pipeline_config,
)
from eval.pipeline import StageRunner, StageSpec, preset
from eval.pipeline.views import read_views, write_views
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.image_metrics import psnr


def test_method_settings():
    base = preset("fast", views=4)
    fam = {m: method_pipeline_config(m, base) for m in EVAL_METHODS if m != "3dgs_gt_poses"}
    # Methods that differ only in rounds share a folder (and so their completed rounds).
    assert {m for m, (f, _) in fam.items() if f == "n2v"} == {"n2v_round1", "denoise_gs", "rounds_1", "rounds_2",
                                                              "rounds_3", "rounds_4"}
    assert fam["n2v_round1"][1].rounds == 1 and fam["denoise_gs"][1].rounds == 2 and fam["rounds_4"][1].rounds == 4
    assert fam["ablate_no_selection"][1].select_views is False
    assert fam["ablate_charbonnier"][1].denoise.round2_loss == "charbonnier"
    assert fam["instantsplat"][1].rounds == 1
    assert fam["oracle_clean"] == ("oracle_clean", fam["instantsplat"][1])  # (b)'s settings, own folder
    assert {m for m, (f, _) in fam.items() if f == "n2v_fused"} == {"n2v_fused_round1", "denoise_gs_fused"}
    # Only the *_fused methods fuse, whatever the preset says (`default` fuses, `fast` does not).
    for name in ("fast", "default"):
        for m in EVAL_METHODS:
            if m != "3dgs_gt_poses":
                assert method_pipeline_config(m, preset(name))[1].fuse_noisy_splat == ("_fused" in m), (name, m)
    with pytest.raises(InputError, match="magic"):
        EvalConfig(methods=("magic",))
    with pytest.raises(InputError, match="seeds"):
        EvalConfig(seeds=0)


def _noisy_folder(tmp_path):
    rng = np.random.default_rng(0)
    clean = cv2.GaussianBlur(rng.random((64, 80, 3)).astype(np.float32), (0, 0), 3.0)
    clean = (clean - clean.min()) / (clean.max() - clean.min())
    noisy = np.clip(clean + rng.normal(0, 25 / 255, clean.shape), 0, 1).astype(np.float32)
    write_views(tmp_path / "noisy", {"a": noisy})
    return clean, tmp_path / "noisy"


@pytest.mark.parametrize("fn", [_identity_stage, _nlm_stage])
def test_classical_denoise_stages(tmp_path, fn):
    clean, folder = _noisy_folder(tmp_path)
    res = StageRunner().run(StageSpec("denoise", tmp_path / "r", fn, ("denoised", "n2v_model.pt"),
                                      inputs={"noisy": folder}))
    out = read_views(res.outputs["denoised"])["a"]
    noisy = read_views(folder)["a"]

    def t(x):
        return __import__("torch").from_numpy(x).permute(2, 0, 1)[None]

    gain = float(psnr(t(out), t(clean))[0] - psnr(t(noisy), t(clean))[0])
    if fn is _identity_stage:
        assert gain == pytest.approx(0.0, abs=0.01)  # 16-bit PNG round trip only
    else:
        # NLM on a smooth image at sigma 25/255: several dB better (measured ~+8 dB); 3 dB is a floor
        # that a broken h/sigma (no-op or over-smoothing to grey) would miss.
        assert gain > 3.0
        assert 0.05 < res.summary["sigma_est"]["a"] < 0.15  # estimate of 25/255 = 0.098


def test_oracle_clean_stage(tmp_path):
    clean, folder = _noisy_folder(tmp_path)
    write_views(tmp_path / "clean", {"a": clean})
    files = {"a": next((tmp_path / "clean").iterdir())}
    stage = functools.partial(_oracle_clean_stage, files)
    res = StageRunner().run(StageSpec("denoise", tmp_path / "r", stage, ("denoised", "n2v_model.pt"),
                                      inputs={"noisy": folder}))
    # The clean photo replaces the noisy one (16-bit PNG round trip: error < 1e-4).
    np.testing.assert_allclose(read_views(res.outputs["denoised"])["a"], clean, atol=1e-4)
    with pytest.raises(InputError, match="no clean image"):
        StageRunner().run(StageSpec("denoise", tmp_path / "r2", functools.partial(_oracle_clean_stage, {}),
                                    ("denoised", "n2v_model.pt"), inputs={"noisy": folder}))


@pytest.mark.parametrize("sigma", [0.02, 0.05, 0.1])
def test_noise_sigma_estimate(sigma):
    from denoise.noise_level import estimate_noise_sigma

    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[0:120, 0:160] / 160.0
    clean = np.stack([0.3 + 0.4 * xx, 0.5 + 0.2 * yy, 0.4 + 0.1 * xx * yy], axis=-1)  # smooth ramps
    noisy = clean + rng.normal(0, sigma, clean.shape)
    # 19k residuals of the channel mean: the estimator's relative standard error is ~2%; 5% leaves margin.
    assert estimate_noise_sigma(noisy) == pytest.approx(sigma, rel=0.05)
