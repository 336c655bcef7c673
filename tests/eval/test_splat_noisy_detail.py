"""`PipelineConfig.splat.noisy_detail`: the splat's target takes back the noisy photos' finest band
(`denoise.detail.noisy_detail_target`). The wiring through `run_pipeline`, the real stage's targets, and the
setting's validation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from denoise.detail import NoisyDetail, noisy_detail_target, noisy_detail_weight
from denoise.self_supervised import r2r_noise_std
from eval.pipeline import PipelineConfig, SplatSettings, preset, run_pipeline
from eval.pipeline.views import read_views
from mvgeo.common.errors import ConfigError
from tests.eval._tiny_stages import TinyStages, make_scene


def test_the_splat_reads_the_noisy_photos_only_when_asked(tmp_path):
    scene = make_scene(tmp_path / "images", n=5)
    stages, seen = TinyStages().spied(
        "splat", lambda ctx: (ctx.work_dir.parent.name, ctx.inputs.get("noisy"), ctx.settings.noisy_detail))
    cfg = dataclasses.replace(preset("fast", views=3, rounds=2), splat=SplatSettings(noisy_detail=0.0))
    run_pipeline(scene, tmp_path / "plain", cfg, stages=stages)
    assert [(r, n) for r, n, _ in seen] == [("round1", None), ("round2", None)]
    assert all(d == NoisyDetail(0.0) for *_, d in seen)
    seen.clear()
    cfg = dataclasses.replace(cfg, splat=SplatSettings(noisy_detail=0.3, noisy_detail_sigma_px=1.5))
    res = run_pipeline(scene, tmp_path / "detail", cfg, stages=stages)
    assert [r for r, *_ in seen] == ["round1", "round2"]
    for _, noisy, detail in seen:
        assert noisy is not None and detail == NoisyDetail(0.3, 1.5)
        # The working photos, every view of them (round 2 reads its selected views' among them).
        assert sorted(read_views(noisy)) == sorted(read_views(res.rounds[0].dir / "denoised"))


def test_the_real_stage_trains_on_the_target(tmp_path, monkeypatch):
    import splat.train
    from eval.pipeline import DenoiseSettings, product_stages

    scene = make_scene(tmp_path / "images", n=4, size_wh=(64, 48))
    tiny = TinyStages()
    stages = dataclasses.replace(product_stages(), denoise=tiny.denoise, align=tiny.align)
    captured = []
    real_train = splat.train.train_gaussians

    def train(images, *args, **kwargs):
        captured.append([np.array(im) for im in images])
        return real_train(images, *args, **kwargs)

    monkeypatch.setattr(splat.train, "train_gaussians", train)
    cfg = dataclasses.replace(preset("default", views=3), denoise=DenoiseSettings(n2v_steps=8, passes=1),
                              splat=SplatSettings(preset="quick", iters=3, noisy_detail=0.5))
    res = run_pipeline(scene, tmp_path / "out", cfg, stages=stages)
    rd = res.rounds[0].dir
    denoised, noisy = read_views(rd / "denoised"), read_views(tmp_path / "out" / "inputs")  # the working photos
    assert len(captured) == 1 and len(captured[0]) == len(denoised)
    summary = res.rounds[0].stages["splat"].summary["noisy_detail"]
    assert (summary["weight"], summary["sigma_px"]) == (0.5, 1.0) and sorted(summary["weights"]) == sorted(denoised)
    for got, k in zip(captured[0], sorted(denoised), strict=True):
        # The view's weight: 0.5 scaled by the photo's estimated noise std (make_scene: 0.05-0.15, some views
        # above the 25/255 reference), as the denoiser estimates it.
        sigma = r2r_noise_std(noisy[k])
        sigma = float(sigma.median()) if not isinstance(sigma, float) else sigma
        assert summary["weights"][k] == pytest.approx(noisy_detail_weight(NoisyDetail(0.5), sigma), rel=1e-12)
        np.testing.assert_array_equal(got, noisy_detail_target(denoised[k], noisy[k], NoisyDetail(0.5), sigma))
        assert np.abs(got - denoised[k]).max() > 0.01  # the noisy photo's band is really there
    assert min(summary["weights"].values()) < 0.5  # the noisiest views' weights were scaled down


@pytest.mark.parametrize(("field", "value", "key"), [("noisy_detail", 1.5, "splat.noisy_detail"),
                                                      ("noisy_detail", -0.1, "splat.noisy_detail"),
                                                      ("noisy_detail_sigma_px", 0.0, "splat.noisy_detail_sigma_px")])
def test_bad_values_are_refused_with_their_key(field, value, key):
    with pytest.raises(ConfigError) as err:
        PipelineConfig(splat=SplatSettings(**{field: value}))
    assert err.value.key == key


def test_only_the_product_takes_the_presets_band():
    """The paper's loop, the baselines, the oracle and the fusion extension train on their photos as they are;
    `product` (and its true-camera variant) take the preset's setting; `eval --noisy-detail` overrides it."""
    from eval.evaluate import EvalConfig, base_pipeline_config
    from eval.methods import METHODS

    base = preset("default")
    assert base.splat.noisy_detail == 0.2 and preset("best").splat.noisy_detail == 0.2
    assert preset("fast").splat.noisy_detail == 0.5
    for name in ("instantsplat", "nlm_instantsplat", "3dgs_gt_poses", "oracle_clean", "n2v_round1", "denoise_gs",
                 "denoise_gs_fused", "ablate_charbonnier"):
        assert METHODS[name].pipeline_config(base).splat.noisy_detail == 0.0, name
    assert METHODS["3dgs_gt_poses"].pipeline_config(base).splat.preset == "gt_poses"
    assert METHODS["product"].pipeline_config(base).splat.noisy_detail == 0.2
    assert METHODS["product@gt_poses"].pipeline_config(base).splat.noisy_detail == 0.2
    assert base_pipeline_config(EvalConfig(noisy_detail=0.0), 12).splat.noisy_detail == 0.0
    assert base_pipeline_config(EvalConfig(), 12).splat.noisy_detail == 0.2
