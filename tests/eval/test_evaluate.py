"""The baselines' stage functions (`eval.baselines`): what they compute and that they write only
`denoised/` (no network, no placeholder checkpoint)."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from eval.baselines import CLASSICAL_DENOISE_OUTPUTS, identity_denoise, nlm_denoise, oracle_clean_denoise
from eval.pipeline import StageRunner, StageSpec
from eval.pipeline.views import read_views, write_views
from mvgeo.common.deps import cv2
from mvgeo.common.errors import InputError
from mvgeo.image_metrics import psnr


def _noisy_folder(tmp_path):
    rng = np.random.default_rng(0)
    clean = cv2.GaussianBlur(rng.random((64, 80, 3)).astype(np.float32), (0, 0), 3.0)
    clean = (clean - clean.min()) / (clean.max() - clean.min())
    noisy = np.clip(clean + rng.normal(0, 25 / 255, clean.shape), 0, 1).astype(np.float32)
    write_views(tmp_path / "noisy", {"a": noisy})
    return clean, tmp_path / "noisy"


@pytest.mark.parametrize("fn", [identity_denoise, nlm_denoise])
def test_classical_denoise_stages(tmp_path, fn):
    clean, folder = _noisy_folder(tmp_path)
    res = StageRunner().run(StageSpec("denoise", tmp_path / "r", fn, CLASSICAL_DENOISE_OUTPUTS,
                                      inputs={"noisy": folder}))
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["denoised", "stages"]  # nothing else
    out = read_views(res.outputs["denoised"])["a"]
    noisy = read_views(folder)["a"]

    def t(x):
        return __import__("torch").from_numpy(x).permute(2, 0, 1)[None]

    gain = float(psnr(t(out), t(clean))[0] - psnr(t(noisy), t(clean))[0])
    if fn is identity_denoise:
        assert gain == pytest.approx(0.0, abs=0.01)  # 16-bit PNG round trip only
    else:
        # NLM on a smooth image at sigma 25/255: several dB better (measured ~+8 dB); 3 dB is a floor
        # that a broken h/sigma (no-op or over-smoothing to grey) would miss.
        assert gain > 3.0
        assert 0.05 < res.summary["sigma_est"]["a"] < 0.15  # estimate of 25/255 = 0.098


def test_oracle_clean_stage(tmp_path):
    clean, folder = _noisy_folder(tmp_path)
    write_views(tmp_path / "clean", {"a": clean})
    res = StageRunner().run(StageSpec("denoise", tmp_path / "r", oracle_clean_denoise, CLASSICAL_DENOISE_OUTPUTS,
                                      inputs={"noisy": folder, "clean": tmp_path / "clean"}, hashed_inputs=("clean",)))
    # The clean photo replaces the noisy one (16-bit PNG round trip: error < 1e-4).
    np.testing.assert_allclose(read_views(res.outputs["denoised"])["a"], clean, atol=1e-4)
    write_views(tmp_path / "other", {"b": clean})
    with pytest.raises(InputError, match="no clean image"):
        StageRunner().run(StageSpec("denoise", tmp_path / "r2", oracle_clean_denoise, CLASSICAL_DENOISE_OUTPUTS,
                                    inputs={"noisy": folder, "clean": tmp_path / "other"}))


def test_changed_clean_photos_rerun_the_oracles_round_1(tmp_path):
    """`oracle_clean`'s denoise stage reads the dataset's clean photos: a changed clean photo (the noisy ones
    unchanged) re-runs it, and its photos are the clean photos as they are now, not those of the first run."""
    from eval.methods import METHODS
    from eval.pipeline import preset, run_pipeline
    from mvgeo.common.imageio import read_image, write_image
    from tests.eval._tiny_stages import TinyStages, tiny_dataset

    ds = tiny_dataset(tmp_path / "ds")
    clean_dir = next(iter(ds.clean.values())).parent
    stages = METHODS["oracle_clean"].stages(ds)
    assert stages.denoise_inputs == {"clean": clean_dir}
    tiny = TinyStages()
    stages = dataclasses.replace(tiny.stages(), denoise=stages.denoise, denoise_outputs=stages.denoise_outputs,
                                 denoise_inputs=stages.denoise_inputs)
    noisy = tmp_path / "noisy"
    noisy.mkdir()
    for n in ds.train:
        shutil.copy(ds.images[n], noisy / ds.images[n].name)
    cfg = dataclasses.replace(preset("fast", views=3, rounds=1), fuse_noisy_splat=False)
    cfg = dataclasses.replace(cfg, splat=dataclasses.replace(cfg.splat, noisy_detail=0.0))
    first = run_pipeline(noisy, tmp_path / "out", cfg, stages=stages)
    assert not first.rounds[0].stages["denoise"].skipped
    changed = ds.clean[ds.train[0]]
    write_image(changed, read_image(changed) * 0.5)  # the clean photo changes, the noisy one does not
    second = run_pipeline(noisy, tmp_path / "out", cfg, stages=stages)
    assert not second.rounds[0].stages["denoise"].skipped
    denoised = read_views(tmp_path / "out" / "round1" / "denoised")[ds.train[0]]
    np.testing.assert_allclose(denoised, read_image(changed), atol=1e-4)


@pytest.mark.parametrize("sigma", [0.02, 0.05, 0.1])
def test_noise_sigma_estimate(sigma):
    from denoise.noise_level import estimate_noise_sigma

    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[0:120, 0:160] / 160.0
    clean = np.stack([0.3 + 0.4 * xx, 0.5 + 0.2 * yy, 0.4 + 0.1 * xx * yy], axis=-1)  # smooth ramps
    noisy = clean + rng.normal(0, sigma, clean.shape)
    # 19k residuals of the channel mean: the estimator's relative standard error is ~2%; 5% leaves margin.
    assert estimate_noise_sigma(noisy) == pytest.approx(sigma, rel=0.05)
