"""Round 1's denoiser (`DenoiseSettings.method`): validation, stage keys, the real stage, the CLIs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eval.cli import main
from eval.evaluate import EvalConfig, base_pipeline_config
from eval.pipeline import preset, run_pipeline
from eval.pipeline.config import DenoiseSettings, PipelineConfig
from eval.pipeline.stage import StageContext
from eval.pipeline.stage_settings import DenoiseStageSettings, n2v_config, round_settings
from eval.pipeline.stages import MODEL_FILE, denoise
from eval.pipeline.views import read_views, write_views
from mvgeo.common.errors import ConfigError, InputError
from tests.eval._tiny_stages import TinyStages, make_scene


def _with_method(config: PipelineConfig, method: str) -> PipelineConfig:
    return dataclasses.replace(config, denoise=dataclasses.replace(config.denoise, method=method))


def test_other_methods_run_round_1_only_and_unknown_ones_are_refused():
    one_round = preset("fast", rounds=1)
    assert _with_method(one_round, "r2r").denoise.method == "r2r"
    with pytest.raises(ConfigError, match="round 1 only"):
        _with_method(preset("fast", rounds=2), "neighbor2neighbor")
    with pytest.raises(ConfigError, match="denoise.method"):
        _with_method(one_round, "bm3d")


def test_the_method_reaches_the_n2v_config_and_only_round_1():
    assert n2v_config(DenoiseSettings(n2v_preset="fast", n2v_steps=5, method="r2r")).method == "r2r"
    assert n2v_config(DenoiseSettings(n2v_preset="fast", n2v_steps=5)).method == "n2v"
    cfg = _with_method(preset("fast", rounds=1), "r2r")
    assert round_settings(cfg, 1).denoise.n2v.method == "r2r"
    # Rounds >= 2 fine-tune the N2V network: their stages carry no round-1 objective.
    later = round_settings(preset("fast", rounds=2), 2)
    assert later.denoise is None and later.refine is not None


def test_changing_the_method_reruns_the_denoise_stage(tmp_path):
    scene = make_scene(tmp_path / "images", n=5)
    out = tmp_path / "out"
    cfg = dataclasses.replace(preset("fast", views=3, rounds=1), fuse_noisy_splat=False)
    tiny = TinyStages()
    run_pipeline(scene, out, cfg, stages=tiny.stages())
    run_pipeline(scene, out, cfg, stages=tiny.stages())
    assert tiny.calls["denoise"] == 1  # same settings: reused
    run_pipeline(scene, out, _with_method(cfg, "r2r"), stages=tiny.stages())
    assert tiny.calls["denoise"] == 2


@pytest.mark.parametrize("method", ["r2r", "neighbor2neighbor"])
def test_the_real_stage_trains_and_applies_the_method(tmp_path, method):
    rng = np.random.default_rng(0)
    clean = np.clip(rng.random((1, 1, 3)) * 0.6 + 0.2 + np.zeros((40, 48, 3)), 0, 1).astype(np.float32)
    noisy = {f"v{i}": np.clip(clean + rng.normal(0, 0.1, clean.shape), 0, 1).astype(np.float32) for i in range(2)}
    write_views(tmp_path / "noisy", noisy)
    settings = DenoiseStageSettings(n2v_config(DenoiseSettings(n2v_preset="fast", n2v_steps=30, method=method)),
                                    passes=2, device="cpu")
    ctx = StageContext(name="denoise", work_dir=tmp_path / "work", inputs={"noisy": tmp_path / "noisy"},
                       settings=settings, seed=0)
    (tmp_path / "work").mkdir()
    summary = denoise(ctx)
    out = read_views(tmp_path / "work" / "denoised")
    assert sorted(out) == sorted(noisy) == summary["views"]
    assert sorted(summary["noise_std_255"]) == sorted(noisy)  # the report's noise level, recorded here
    assert (tmp_path / "work" / "n2v_model.pt").is_file()
    # A flat patch: any sensible denoiser lowers the error to it (30 steps; the noisy error is 0.1^2).
    err_noisy = np.mean([(noisy[k] - clean) ** 2 for k in noisy])
    err_out = np.mean([(out[k] - clean) ** 2 for k in out])
    assert err_out < 0.8 * err_noisy, (err_out, err_noisy)


def test_eval_refuses_multi_round_methods_with_another_denoiser():
    EvalConfig(methods=("instantsplat", "n2v_fused_round1"), denoiser="r2r")
    with pytest.raises(InputError, match="round 1 only"):
        EvalConfig(methods=("n2v_round1", "denoise_gs"), denoiser="r2r")


def test_run_cli_refuses_two_rounds_with_r2r_before_any_work(tmp_path, capsys):
    scene = make_scene(tmp_path / "images", n=3)
    assert main(["run", str(scene), "--out", str(tmp_path / "o"), "--denoiser", "r2r", "--rounds", "2"]) == 2
    err = capsys.readouterr().err
    assert "round 1 only" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    # the default preset's own objective is R2R: asking it for two rounds is refused the same way
    assert main(["run", str(scene), "--out", str(tmp_path / "o"), "--rounds", "2"]) == 2
    assert "round 1 only" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_results_rows_name_the_denoiser():
    from eval.methods import METHODS

    assert METHODS["n2v_round1"].row_label("r2r") == "n2v_round1+r2r"
    assert METHODS["n2v_fused_round1"].row_label("neighbor2neighbor") == "n2v_fused_round1+neighbor2neighbor"
    assert METHODS["instantsplat"].row_label("r2r") == "instantsplat"
    assert METHODS["n2v_round1"].row_label("n2v") == "n2v_round1"
    # The folder follows the label: N2V's runs are not reused for another objective.
    assert (METHODS["n2v_round1"].folder("r2r"), METHODS["n2v_round1"].folder("n2v")) == ("n2v_r2r", "n2v")
    assert METHODS["n2v_round1"].pipeline_config(preset("fast"), "r2r").denoise.method == "r2r"
    assert METHODS["instantsplat"].pipeline_config(preset("fast"), "r2r").denoise.method == "n2v"


def _flat_noisy_photos(folder, seed: int, shape=(40, 48, 3)) -> dict[str, np.ndarray]:
    """Two photos of one flat random colour with noise of std 0.1, written to `folder`."""
    rng = np.random.default_rng(seed)
    clean = np.clip(rng.random((1, 1, 3)) * 0.6 + 0.2 + np.zeros(shape), 0, 1).astype(np.float32)
    noisy = {f"v{i}": np.clip(clean + rng.normal(0, 0.1, clean.shape), 0, 1).astype(np.float32) for i in range(2)}
    write_views(folder, noisy)
    return noisy


def _run_denoise_stage(tmp_path, work_name: str, steps: int, **settings):
    """The real denoise stage (R2R, the fast preset, `steps` steps) on `tmp_path / "noisy"` into
    `tmp_path / work_name`: (its summary, the photos it wrote)."""
    work = tmp_path / work_name
    work.mkdir()
    stage = DenoiseStageSettings(n2v_config(DenoiseSettings(n2v_preset="fast", n2v_steps=steps, method="r2r")),
                                 passes=1, device="cpu", **settings)
    summary = denoise(StageContext(name="denoise", work_dir=work, inputs={"noisy": tmp_path / "noisy"},
                                   settings=stage, seed=0))
    return summary, read_views(work / "denoised")


def test_keep_noisy_blends_the_noisy_photo_back_in(tmp_path):
    # The stage with keep_noisy k writes (1 - k) * the network's output + k * the noisy photo: against the
    # same seeded stage with k = 0 and the formula (8-bit PNGs: one level of rounding).
    noisy = _flat_noisy_photos(tmp_path / "noisy", 1)
    outs = {k: _run_denoise_stage(tmp_path, f"work{k}", 5, keep_noisy=k)[1] for k in (0.0, 0.3)}
    noisy_read = read_views(tmp_path / "noisy")
    for name in noisy:
        expected = 0.7 * outs[0.0][name] + 0.3 * noisy_read[name]
        assert np.abs(outs[0.3][name] - expected).max() <= 1.01 / 255
        assert np.abs(outs[0.3][name] - outs[0.0][name]).max() > 5 / 255  # the blend changed the photos


def test_keep_noisy_is_validated_and_reaches_the_stage(tmp_path, capsys):
    with pytest.raises(ConfigError, match="denoise.keep_noisy"):
        dataclasses.replace(preset("default"), denoise=dataclasses.replace(preset("default").denoise, keep_noisy=1.0))
    cfg = preset("default")
    assert round_settings(cfg, 1).denoise.keep_noisy == cfg.denoise.keep_noisy
    scene = make_scene(tmp_path / "images", n=3)
    with pytest.raises(SystemExit) as exc:  # the option as typed, checked by the parser
        main(["run", str(scene), "--out", str(tmp_path / "o"), "--keep-noisy", "-0.1"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "argument --keep-noisy: must be a number in [0, 1)" in err
    assert "Traceback" not in err and not (tmp_path / "o").exists()


def test_auto_chooses_the_objective_from_the_photos_in_the_stage(tmp_path):
    # `default` ships "auto": R2R in the config, the stage choosing for the photos it gets.
    assert preset("default").denoise.method == "auto"
    settings = round_settings(preset("default"), 1).denoise
    assert settings.choose_objective and settings.n2v.method == "r2r"
    assert not round_settings(_with_method(preset("default"), "r2r"), 1).denoise.choose_objective
    with pytest.raises(ConfigError, match="round 1 only"):
        _with_method(preset("fast", rounds=2), "auto")
    rng = np.random.default_rng(0)
    clean = np.full((40, 48, 3), 0.6, np.float32)
    clean[:, :30] = 0.0  # a black background over most of the photo
    noisy = {f"v{i}": np.clip(clean + rng.normal(0, 0.1, clean.shape), 0, 1).astype(np.float32) for i in range(2)}
    write_views(tmp_path / "noisy", noisy)
    small = DenoiseStageSettings(n2v_config(DenoiseSettings(n2v_preset="fast", n2v_steps=5, method="auto")),
                                 passes=1, device="cpu", choose_objective=True)
    ctx = StageContext(name="denoise", work_dir=tmp_path / "work", inputs={"noisy": tmp_path / "noisy"},
                       settings=small, seed=0)
    (tmp_path / "work").mkdir()
    summary = denoise(ctx)
    assert summary["objective"] == "neighbor2neighbor" and summary["dark_clipped_fraction"] > 0.5


def test_the_wiener_step_is_a_setting_of_round_1_that_reruns_the_denoise_stage(tmp_path):
    from denoise.wiener import WienerConfig

    # Every preset refines its round-1 photos with it.
    for name in ("default", "best", "fast"):
        assert round_settings(preset(name), 1).denoise.wiener == WienerConfig()
    scene = make_scene(tmp_path / "images", n=5)
    out = tmp_path / "out"
    cfg = dataclasses.replace(preset("fast", views=3, rounds=1), fuse_noisy_splat=False)
    cfg = dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, wiener=False))
    assert round_settings(cfg, 1).denoise.wiener is None
    tiny = TinyStages()
    run_pipeline(scene, out, cfg, stages=tiny.stages())
    on = dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, wiener=True))
    run_pipeline(scene, out, on, stages=tiny.stages())
    assert tiny.calls["denoise"] == 2  # its key holds the step's configuration


def test_the_grouped_wiener_step_is_a_setting_of_default_and_best(tmp_path):
    from denoise.grouped_wiener import GroupedWienerConfig

    for name in ("default", "best"):
        assert round_settings(preset(name), 1).denoise.grouped == GroupedWienerConfig()
    assert round_settings(preset("fast"), 1).denoise.grouped is None
    scene = make_scene(tmp_path / "images", n=5)
    out = tmp_path / "out"
    cfg = dataclasses.replace(preset("fast", views=3, rounds=1), fuse_noisy_splat=False)
    tiny = TinyStages()
    run_pipeline(scene, out, cfg, stages=tiny.stages())
    on = dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, grouped_wiener=True))
    run_pipeline(scene, out, on, stages=tiny.stages())
    assert tiny.calls["denoise"] == 2  # its key holds the step's configuration


def _stage_errors(tmp_path, variants: dict[object, DenoiseSettings]) -> dict[object, float]:
    """The real denoise stage on two noisy copies of a textured photo, once per settings variant: each
    variant's mean squared error against the clean photo."""
    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[0:40, 0:48] / 3.0
    base = 0.5 + 0.2 * np.sin(xx) * np.cos(0.7 * yy)
    clean = np.stack([base, 0.9 * base, 1.0 - base], axis=-1).astype(np.float32)
    noisy = {f"v{i}": np.clip(clean + rng.normal(0, 0.1, clean.shape), 0, 1).astype(np.float32) for i in range(2)}
    write_views(tmp_path / "noisy", noisy)
    errors = {}
    for i, (key, d) in enumerate(variants.items()):
        settings = round_settings(dataclasses.replace(preset("fast", rounds=1), denoise=d), 1).denoise
        work = tmp_path / f"work{i}"
        work.mkdir()
        denoise(StageContext(name="denoise", work_dir=work, inputs={"noisy": tmp_path / "noisy"},
                             settings=dataclasses.replace(settings, device="cpu"), seed=0))
        out = read_views(work / "denoised")
        errors[key] = float(np.mean([(out[k] - clean) ** 2 for k in noisy]))
    return errors


def test_the_real_stage_applies_the_grouped_wiener_step(tmp_path):
    # On a textured photo the grouped step after the DCT step brings the stage's photos closer to the clean
    # one than the DCT step alone (0.15x its error on this smooth, self-similar pattern).
    variants = {g: DenoiseSettings(n2v_preset="fast", n2v_steps=30, method="r2r", wiener=True, grouped_wiener=g)
                for g in (False, True)}
    for g, d in variants.items():
        settings = round_settings(dataclasses.replace(preset("fast", rounds=1), denoise=d), 1).denoise
        assert (settings.grouped is not None) == g
    err = _stage_errors(tmp_path, variants)
    assert err[True] < 0.5 * err[False], err


def test_the_real_stage_applies_the_wiener_step(tmp_path):
    # The stage with the step writes what the stage without it writes, refined: closer to the clean photo on a
    # textured one (a 30-step network leaves most of the texture to recover; 0.55x its error here).
    n2v = n2v_config(DenoiseSettings(n2v_preset="fast", n2v_steps=30, method="r2r"))
    variants = {w: DenoiseSettings(n2v_preset="fast", n2v_steps=30, method="r2r", wiener=w) for w in (False, True)}
    for w, d in variants.items():
        settings = round_settings(dataclasses.replace(preset("fast", rounds=1), denoise=d), 1).denoise
        assert settings.n2v == n2v and (settings.wiener is not None) == w
    err = _stage_errors(tmp_path, variants)
    assert err[True] < 0.9 * err[False], err


def test_an_evaluation_can_turn_the_grouped_wiener_step_on_or_off():
    from eval.evaluate import EvalConfig, base_pipeline_config

    assert base_pipeline_config(EvalConfig(methods=("product",)), 12).denoise.grouped_wiener  # the preset's
    for on in (False, True):
        cfg = EvalConfig(methods=("product",), grouped_wiener=on)
        assert base_pipeline_config(cfg, 12).denoise.grouped_wiener is on
    fast = EvalConfig(methods=("product",), preset="fast")
    assert not base_pipeline_config(fast, 12).denoise.grouped_wiener
    assert base_pipeline_config(dataclasses.replace(fast, grouped_wiener=True), 12).denoise.grouped_wiener


def test_the_stage_denoises_pixel_shuffled_sub_images_at_the_stride_given(tmp_path, monkeypatch):
    import eval.pipeline.stages as stages

    seen = []
    real = stages._denoise_photos

    def spy(photos, *args, **kwargs):
        seen.append([p.shape for p in photos])
        return real(photos, *args, **kwargs)

    monkeypatch.setattr(stages, "_denoise_photos", spy)
    noisy = _flat_noisy_photos(tmp_path / "noisy", 3, (40, 46, 3))
    summaries = {}
    for stride in (0, 2):
        summaries[stride], out = _run_denoise_stage(tmp_path, f"work{stride}", 3, pd_stride=stride)
        assert {k: v.shape for k, v in out.items()} == {k: v.shape for k, v in noisy.items()}
    assert summaries[2]["pd_stride"] == 2 and summaries[0]["pd_stride"] == 1  # too small to measure: none
    # Stride 1 denoised the two 40 x 46 photos; stride 2 their eight 20 x 23 sub-images.
    assert seen == [[(40, 46, 3)] * 2, [(20, 23, 3)] * 8]
    # The report's noise level per photo comes back from its four sub-images' (about the true 0.1).
    assert all(15 < v < 40 for v in summaries[2]["noise_std_255"].values())


def _clean_photos(folder, n: int = 2, shape=(48, 56, 3)) -> dict[str, np.ndarray]:
    """`n` smooth textured 8-bit photos without noise (their level reads at the estimator's floor, 0.5/255)."""
    h, w, _ = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    photos = {}
    for i in range(n):
        phase = np.random.default_rng(i).random(3) * 6
        img = np.stack([0.5 + 0.3 * np.sin(x / 5 + p) * np.cos(y / 7 - p) for p in phase], -1)
        photos[f"v{i}"] = (np.round(img * 255) / 255).astype(np.float32)
    write_views(folder, photos)
    return photos


def test_photos_that_read_clean_pass_through_without_a_network(tmp_path):
    """`pass_clean_below_255`: photos whose every level reads under it are written as they are and no network
    is trained; noisy photos, or the setting at 0, train as before."""
    clean = _clean_photos(tmp_path / "noisy")
    summary, out = _run_denoise_stage(tmp_path, "passed", 3, pass_clean_below_255=1.5)
    assert summary["passed_through"] is True and "train" not in summary
    assert not (tmp_path / "passed" / MODEL_FILE).exists()
    assert all(np.array_equal(out[k], clean[k]) for k in clean)  # the photos, bit for bit
    assert all(v < 1.5 for v in summary["noise_std_255"].values())
    summary, out = _run_denoise_stage(tmp_path, "always", 3, pass_clean_below_255=0.0)
    assert "passed_through" not in summary and summary["train"]["loss"]["count"] == 3
    assert (tmp_path / "always" / MODEL_FILE).is_file()
    _flat_noisy_photos(tmp_path / "noisy", 5)  # sigma 0.1 = 25.5/255 over the same names: trained
    summary, _ = _run_denoise_stage(tmp_path, "trained", 3, pass_clean_below_255=1.5)
    assert "passed_through" not in summary and summary["train"]["loss"]["count"] == 3
    assert (tmp_path / "trained" / MODEL_FILE).is_file()


def test_the_pass_through_rule_reads_every_photos_level():
    from eval.pipeline.stages import _reads_clean

    torch = pytest.importorskip("torch")
    assert _reads_clean([0.5 / 255, 1.49 / 255], 1.5)
    assert not _reads_clean([0.5 / 255, 1.51 / 255], 1.5)  # one photo over it: all are denoised
    assert not _reads_clean([0.5 / 255], 0.0)  # 0: never
    level_map = torch.full((3, 4, 4), 1.0 / 255)
    level_map[0, 0, :3] = 9.0 / 255  # a per-pixel level counts by its median, as the report reads it
    assert _reads_clean([level_map], 1.5) and not _reads_clean([level_map * 2], 1.5)


def test_the_pass_through_setting_is_validated_and_reaches_the_stage(tmp_path, capsys):
    from eval.methods import METHODS
    from eval.pipeline.config import PASS_CLEAN_BELOW_255

    for name in ("fast", "default", "best"):
        assert round_settings(preset(name), 1).denoise.pass_clean_below_255 == PASS_CLEAN_BELOW_255
    assert DenoiseSettings().pass_clean_below_255 == 0.0  # the paper's: always denoise
    assert METHODS["denoise_gs"].configure(preset("default")).denoise.pass_clean_below_255 == 0.0
    for bad in (-1.0, 300.0, True, float("nan"), "1"):
        with pytest.raises(ConfigError, match="denoise.pass_clean_below_255"):
            dataclasses.replace(preset("default"), denoise=dataclasses.replace(preset("default").denoise,
                                                                              pass_clean_below_255=bad))
    cfg = base_pipeline_config(EvalConfig(methods=("product",), pass_clean_below=0.0), views=4)
    assert cfg.denoise.pass_clean_below_255 == 0.0
    scene = make_scene(tmp_path / "images", n=3)
    with pytest.raises(SystemExit) as exc:  # argparse's own refusal: exit 2, the option named
        main(["run", str(scene), "--out", str(tmp_path / "o"), "--pass-clean-below", "-1"])
    assert exc.value.code == 2
    assert "--pass-clean-below" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_pd_stride_is_validated_and_reaches_the_stage(tmp_path, capsys):
    cfg = preset("default")
    assert cfg.denoise.pd_stride == 0 and round_settings(cfg, 1).denoise.pd_stride == 0
    for bad in (5, -1, True, 2.0):
        with pytest.raises(ConfigError, match="denoise.pd_stride"):
            dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, pd_stride=bad))
    # Round 1's stage settings do not depend on the rounds that follow (their stages are shared); the refine
    # stage of rounds >= 2 takes the same stride setting.
    two = dataclasses.replace(preset("fast", rounds=2), denoise=dataclasses.replace(preset("fast").denoise,
                                                                                      pd_stride=2))
    assert round_settings(two, 1).denoise == round_settings(dataclasses.replace(two, rounds=1), 1).denoise
    assert round_settings(two, 2).refine.pd_stride == 2
    assert base_pipeline_config(EvalConfig(methods=("product",), pd_stride=3), views=4).denoise.pd_stride == 3
    scene = make_scene(tmp_path / "images", n=3)
    with pytest.raises(SystemExit) as exc:  # argparse's own refusal: exit 2, the option named
        main(["run", str(scene), "--out", str(tmp_path / "o"), "--pd-stride", "5"])
    assert exc.value.code == 2
    assert "--pd-stride" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_the_noise_model_setting_overrides_the_measured_one(tmp_path, monkeypatch):
    """`DenoiseSettings.noise_model`: None reads the level as the photos' noise is found (white noise in
    PNGs: "auto", the colour patches); a model given is the one the denoisers use, whatever was found."""
    import eval.pipeline.stages as stages

    seen = []
    real = stages._denoise_photos

    def spy(photos, n2v, s, seed, noise_model, stds):
        seen.append(noise_model)
        return real(photos, n2v, s, seed, noise_model, stds)

    monkeypatch.setattr(stages, "_denoise_photos", spy)
    _flat_noisy_photos(tmp_path / "noisy", 2, (40, 46, 3))
    stds = {}
    for model in (None, "luma"):
        summary, _ = _run_denoise_stage(tmp_path, f"work_{model}", 3, noise_model=model)
        stds[model] = summary["noise_std_255"]
    assert seen == ["auto", "luma"]
    # White noise reads alike on the colour patches and the luma (the luma's RGB-equivalent level): the
    # override changes the model, not the noise (about the true 0.1 = 25.5/255 both ways).
    assert all(15 < v < 40 for m in stds.values() for v in m.values()), stds

    cfg = preset("default")
    assert cfg.denoise.noise_model is None and round_settings(cfg, 1).denoise.noise_model is None
    luma = dataclasses.replace(preset("fast", rounds=2), denoise=dataclasses.replace(preset("fast").denoise,
                                                                                       noise_model="luma"))
    assert round_settings(luma, 1).denoise.noise_model == "luma"
    assert round_settings(luma, 2).refine.noise_model == "luma"
    with pytest.raises(ConfigError, match="denoise.noise_model"):
        dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, noise_model="gray"))
    for model in (None, "luma"):
        cfg = EvalConfig(methods=("product",), noise_model=model)
        assert base_pipeline_config(cfg, views=4).denoise.noise_model == model


def test_the_cli_noise_model_choices_are_the_denoisers(tmp_path, capsys):
    import eval.cli
    from denoise.inference import NOISE_MODELS

    assert eval.cli.NOISE_MODEL_CHOICES == NOISE_MODELS
    scene = make_scene(tmp_path / "images", n=3)
    with pytest.raises(SystemExit) as exc:
        main(["run", str(scene), "--out", str(tmp_path / "o"), "--noise-model", "gray"])
    assert exc.value.code == 2 and "--noise-model" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_the_refine_stage_fine_tunes_and_denoises_the_sub_images_at_round_1s_stride(tmp_path, monkeypatch):
    import denoise.round2 as round2
    from eval.pipeline.stage_settings import RefineStageSettings, round2_config
    from eval.pipeline.stages import refine

    noisy = _flat_noisy_photos(tmp_path / "noisy", 4, (40, 46, 3))
    write_views(tmp_path / "renders", {k: np.full((40, 46, 3), 0.5, np.float32) for k in noisy})
    (tmp_path / "selection.json").write_text('{"names": ["v0", "v1"]}')
    d = DenoiseSettings(n2v_preset="fast", n2v_steps=3, round2_steps=2)
    (tmp_path / "r1").mkdir()
    denoise(StageContext(name="denoise", work_dir=tmp_path / "r1", inputs={"noisy": tmp_path / "noisy"},
                         settings=DenoiseStageSettings(n2v_config(d), passes=1, device="cpu", pd_stride=2), seed=0))
    seen = []
    real = round2.refine_round2

    def spy(model, photos, renders, *args, **kwargs):
        seen.append(([p.shape for p in photos], [r.shape for r in renders]))
        return real(model, photos, renders, *args, **kwargs)

    monkeypatch.setattr(round2, "refine_round2", spy)
    (tmp_path / "r2").mkdir()
    summary = refine(StageContext(
        name="refine", work_dir=tmp_path / "r2", seed=0,
        inputs={"selection": tmp_path / "selection.json", "noisy": tmp_path / "noisy", "renders": tmp_path / "renders",
                "model": tmp_path / "r1" / "n2v_model.pt"},
        settings=RefineStageSettings(round2_config(d), passes=1, device="cpu", pd_stride=2)))
    assert summary["pd_stride"] == 2
    assert seen == [([(20, 23, 3)] * 8, [(20, 23, 3)] * 8)]  # photos and renders shuffled alike
    assert {k: v.shape for k, v in read_views(tmp_path / "r2" / "denoised").items()} == {"v0": (40, 46, 3),
                                                                                        "v1": (40, 46, 3)}


def test_grouped_wiener_passes_are_validated_and_reach_the_stage(tmp_path):
    from denoise.grouped_wiener import GroupedWienerConfig

    cfg = preset("default")
    assert cfg.denoise.grouped_wiener_passes == 1
    for bad in (0, -1, True, 2.0, 11, 1_000_000):
        with pytest.raises(ConfigError, match="denoise.grouped_wiener_passes"):
            dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, grouped_wiener_passes=bad))
    two = dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, grouped_wiener_passes=2))
    assert round_settings(two, 1).denoise.grouped == GroupedWienerConfig(passes=2)
    ten = dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, grouped_wiener_passes=10))
    assert ten.denoise.grouped_wiener_passes == 10
    scene = make_scene(tmp_path / "images", n=3)
    with pytest.raises(SystemExit) as exc:  # argparse's own refusal: exit 2, the option named
        main(["run", str(scene), "--out", str(tmp_path / "o"), "--grouped-wiener-passes", "0"])
    assert exc.value.code == 2


def test_grouped_wiener_passes_on_the_command_line(tmp_path, monkeypatch, capsys):
    import eval.cli as cli

    seen = []
    monkeypatch.setattr(cli, "run_pipeline", lambda images, out, config, force: seen.append(config) or _Result())
    scene = make_scene(tmp_path / "images", n=3)
    assert main(["run", str(scene), "--out", str(tmp_path / "o"), "--preset", "fast",
                 "--grouped-wiener-passes", "2"]) == 0
    assert seen[-1].denoise.grouped_wiener and seen[-1].denoise.grouped_wiener_passes == 2  # turns the step on
    assert main(["run", str(scene), "--out", str(tmp_path / "o"), "--no-grouped-wiener",
                 "--grouped-wiener-passes", "2"]) == 2  # contradictory: refused, nothing run
    assert len(seen) == 1 and "give one of the two options" in capsys.readouterr().err


class _Result:
    report_md = "report.md"


def test_an_evaluation_can_set_the_grouped_wiener_passes():
    from mvgeo.common.errors import InputError

    base = base_pipeline_config(EvalConfig(methods=("product",), preset="fast", grouped_wiener_passes=2), views=4)
    assert base.denoise.grouped_wiener and base.denoise.grouped_wiener_passes == 2  # turned on, as `run` does
    assert base_pipeline_config(EvalConfig(methods=("product",)), views=4).denoise.grouped_wiener_passes == 1
    with pytest.raises(InputError, match="grouped-wiener-passes"):
        EvalConfig(methods=("product",), grouped_wiener=False, grouped_wiener_passes=2)
