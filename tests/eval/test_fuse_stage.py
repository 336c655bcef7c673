"""The fuse extension (`PipelineConfig.fuse_noisy_splat`): the arithmetic, the wiring through
`run_pipeline`, and the real stage with the real splat (a few steps)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eval.methods import METHODS
from eval.pipeline import preset, run_pipeline
from eval.pipeline.fuse_stage import FUSE_WEIGHT, fuse_images
from eval.pipeline.views import read_views
from tests.eval._tiny_stages import TinyStages, make_scene


def test_fuse_images_is_the_weighted_mean():
    rng = np.random.default_rng(0)
    a, b = rng.random((4, 5, 3)), rng.random((4, 5, 3))
    np.testing.assert_allclose(fuse_images(a, b), (1 - FUSE_WEIGHT) * a + FUSE_WEIGHT * b, atol=1e-7)
    np.testing.assert_allclose(fuse_images(a, b, 0.0), a, atol=1e-7)
    with pytest.raises(ValueError, match="shape"):
        fuse_images(a, b[:3])


def test_pipeline_runs_fuse_before_each_splat_only_when_asked(tmp_path):
    scene = make_scene(tmp_path / "images", n=5)
    seen = []
    tiny = TinyStages()

    def splat(ctx):
        seen.append((ctx.work_dir.parent.name, ctx.inputs["images"].name))
        return tiny.splat(ctx)

    stages = dataclasses.replace(tiny.stages(), splat=splat)
    cfg = dataclasses.replace(preset("fast", views=3, rounds=2), fuse_noisy_splat=False)
    res = run_pipeline(scene, tmp_path / "plain", cfg, stages=stages)
    assert tiny.calls["fuse"] == 0 and seen == [("round1", "denoised"), ("round2", "denoised")]
    assert "fuse" not in res.rounds[0].stages
    seen.clear()
    res = run_pipeline(scene, tmp_path / "fused", dataclasses.replace(cfg, fuse_noisy_splat=True), stages=stages)
    assert tiny.calls["fuse"] == 2 and seen == [("round1", "fused"), ("round2", "fused")]
    r2 = res.rounds[1].dir
    assert sorted(read_views(r2 / "fused")) == sorted(read_views(r2 / "denoised"))  # the selected views
    # The eval methods of the extension share a folder family of their own.
    fused = METHODS["denoise_gs_fused"]
    mcfg = fused.pipeline_config(cfg)
    assert fused.family == "n2v_fused" and mcfg.fuse_noisy_splat and mcfg.rounds == 2
    assert METHODS["n2v_fused_round1"].pipeline_config(cfg).rounds == 1


@pytest.mark.slow  # real splat training (a few steps) twice
def test_real_fuse_stage(tmp_path):
    from eval.pipeline import DenoiseSettings, SplatSettings, product_stages

    scene = make_scene(tmp_path / "images", n=4, size_wh=(64, 48))
    tiny = TinyStages()
    stages = dataclasses.replace(product_stages(), denoise=tiny.denoise, align=tiny.align)
    cfg = dataclasses.replace(preset("fast", views=3, rounds=1), fuse_noisy_splat=True,
                              denoise=DenoiseSettings(n2v_preset="fast", n2v_steps=8, passes=1),
                              splat=SplatSettings(preset="quick", iters=5))
    res = run_pipeline(scene, tmp_path / "out", cfg, stages=stages)
    rd = res.rounds[0].dir
    denoised, renders, fused = (read_views(rd / d) for d in ("denoised", "noisy_renders", "fused"))
    assert sorted(fused) == sorted(denoised) == sorted(renders)
    for k in fused:
        assert renders[k].shape == denoised[k].shape
        # Three 16-bit PNG round trips (1.5e-5 each at most): within 5e-5 of the weighted mean.
        np.testing.assert_allclose(fused[k], fuse_images(denoised[k], renders[k]), atol=5e-5)
    assert res.rounds[0].stages["fuse"].summary["weight"] == FUSE_WEIGHT
