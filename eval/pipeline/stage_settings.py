"""The typed settings each product stage receives (`StageContext.settings`), resolved from a `PipelineConfig`.

A stage gets the configuration objects its components run with: the round-1 denoise stage the
`denoise.n2v.N2VConfig` (the preset named by `DenoiseSettings.n2v_preset` with the setting's
overrides), the align stage the `mvgeo.align.AlignConfig`, the fuse and splat stages the
`splat.train.TrainConfig`, the refine stage the `denoise.round2.Round2Config`, each with the few
run-level values it needs (device, inference passes, K, and for the fuse stage of rounds >= 2
`PipelineConfig.reuse_noisy_splat`). What a stage runs is what its key hashes
(`eval.pipeline.stage.settings_json`): a changed preset default re-runs the stages that use it and
the stages after them, and a setting a stage does not use is not in its key (round 2's loss does
not re-run round 1).

Seeds: the component configs that carry a seed (`AlignConfig.seed`, `TrainConfig.seed`) get the
stage's own seed, `stage_seed(config.seed, round, stage)`, which is also the `StageSpec.seed`.

Resolution imports the component packages when called, not when this module is imported: they
load torch, which the settings classes themselves do not need.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

from denoise.detail import NoisyDetail  # numpy only
from eval.pipeline.config import (
    AlignPhotos,
    AlignSettings,
    DenoiseSettings,
    PipelineConfig,
    ReuseGeometry,
    ReuseIntrinsics,
    SplatSettings,
)
from eval.pipeline.hashing import hash_json
from mvgeo.common.errors import ConfigError

if TYPE_CHECKING:
    from denoise.grouped_wiener import GroupedWienerConfig
    from denoise.n2v import N2VConfig
    from denoise.round2 import Round2Config
    from denoise.wiener import WienerConfig
    from mvgeo.align import AlignConfig
    from splat.train import TrainConfig

__all__ = ["ALIGN_PRESETS", "AlignStageSettings", "DenoiseStageSettings", "FuseStageSettings", "InputsStageSettings",
           "RefineStageSettings", "RenderStageSettings", "RoundSettings", "SelectStageSettings",
           "SplatStageSettings", "align_config", "check_settings", "n2v_config", "round2_config",
           "round_settings", "stage_seed", "train_config"]

#: `AlignSettings.preset` names: "default" is `mvgeo.align.AlignConfig()`, "preview" `mvgeo.align.PREVIEW`.
ALIGN_PRESETS = ("default", "preview")
#: `DenoiseSettings.round2_preset` names: `denoise.round2` has no preset table; "default" is `Round2Config()`.
ROUND2_PRESETS = ("default",)


def stage_seed(seed: int, round_index: int, stage: str) -> int:
    """A stage's seed, derived from the master seed, the round and the stage name (31 bits)."""
    return int(hash_json([seed, round_index, stage])[:8], 16) & 0x7FFFFFFF


@dataclass(frozen=True)
class InputsStageSettings:
    """Stage `inputs` (`eval.pipeline.inputs.prepare_inputs`).

    Attributes:
        max_size: long side in pixels of the working images; None keeps the input size.
        noisy_digest: content digest of the input images (`hash_files`): the stage reads a folder
            outside the run, so its content enters the key through this field.
    """

    max_size: int | None
    noisy_digest: str


@dataclass(frozen=True)
class DenoiseStageSettings:
    """Round 1's denoise stage.

    Attributes:
        n2v: the UNet's training configuration (its `method` is round 1's objective).
        passes: inference maskings averaged per image; 0: one pass on the unmasked image.
        device: torch device.
        keep_noisy: fraction of the noisy photo in the written photos (`DenoiseSettings.keep_noisy`).
        choose_objective: `n2v.method` is replaced by `denoise.self_supervised.choose_objective`'s choice
            for the photos (`DenoiseSettings.method="auto"`; `n2v.method` is then "r2r").
        wiener: the DCT Wiener step on the network's outputs (`DenoiseSettings.wiener`); None: off.
        grouped: the grouped Wiener step after it (`DenoiseSettings.grouped_wiener`); None: off.
        pd_stride: pixel-shuffle stride of the denoising (`DenoiseSettings.pd_stride`): 0 measured from the
            photos, 1 off.
        noise_model: how each photo's noise level is read (`DenoiseSettings.noise_model`); None: as
            `denoise.pixel_shuffle.choose_stride` finds the noise.
        pass_clean_below_255: photos whose noise reads under this level (/255) on every photo pass through
            undenoised (`DenoiseSettings.pass_clean_below_255`); 0: always denoise.
    """

    n2v: N2VConfig
    passes: int
    device: str
    keep_noisy: float = 0.0
    choose_objective: bool = False
    wiener: WienerConfig | None = None
    grouped: GroupedWienerConfig | None = None
    pd_stride: int = 0
    noise_model: str | None = None
    pass_clean_below_255: float = 0.0


@dataclass(frozen=True)
class RefineStageSettings:
    """The refine stage of rounds >= 2.

    Attributes:
        round2: the fine-tuning configuration (loss, steps).
        passes: inference maskings averaged per image; 0: one pass on the unmasked image.
        device: torch device.
        pd_stride: pixel-shuffle stride of the fine-tuning and inference, as round 1's
            (`DenoiseSettings.pd_stride`; 0: the runner puts in the stride round 1 measured,
            `eval.pipeline.run.refine_settings_as_round1`).
        noise_model: as round 1's (`DenoiseSettings.noise_model`; None: the runner puts in the one round 1
            measured).
    """

    round2: Round2Config
    passes: int
    device: str
    pd_stride: int = 0
    noise_model: str | None = None


@dataclass(frozen=True)
class AlignStageSettings:
    """The align stage.

    Attributes:
        align: the alignment configuration, seed included.
        reuse_intrinsics, reuse_geometry: `AlignSettings`' rules for rounds >= 2; None in round 1,
            which has no previous round (so that changing them never re-runs round 1).
        photos: which photos round 1 aligns (`AlignSettings.photos`); rounds >= 2 align their denoised
            photos ("denoised").
    """

    align: AlignConfig
    reuse_intrinsics: ReuseIntrinsics | None = None
    reuse_geometry: ReuseGeometry | None = None
    photos: AlignPhotos = "denoised"

    @property
    def reads_noisy(self) -> bool:
        """Whether the stage aligns the noisy photos too (it then needs them as an input)."""
        return self.photos != "denoised"


@dataclass(frozen=True)
class SplatStageSettings:
    """The splat stage.

    Attributes:
        train: the training configuration, seed included.
        device: torch device.
        noisy_detail: the noisy photos' finest band in the target (`PipelineConfig.splat.noisy_detail`);
            weight 0 trains on the round's images as they are.
    """

    train: TrainConfig
    device: str
    noisy_detail: NoisyDetail = NoisyDetail()


@dataclass(frozen=True)
class FuseStageSettings:
    """The fuse stage (`PipelineConfig.fuse_noisy_splat`), which trains a splat of the noisy photos.

    Attributes:
        train: the noisy-photo splat's training configuration, seed included.
        device: torch device.
        reuse_noisy_splat: `PipelineConfig.reuse_noisy_splat`; None in round 1, which has no previous
            round (so that changing it never re-runs round 1).
    """

    train: TrainConfig
    device: str
    reuse_noisy_splat: bool | None = None


@dataclass(frozen=True)
class RenderStageSettings:
    """The render stage. Attributes: device: torch device."""

    device: str


@dataclass(frozen=True)
class SelectStageSettings:
    """The select stage of rounds >= 2.

    Attributes:
        views: K, the number of views kept.
        select_views: False keeps every view (Table 2 ablation).
    """

    views: int
    select_views: bool


@dataclass(frozen=True)
class RoundSettings:
    """The settings of one round's stages (`round_settings`); None where the round has no such stage."""

    index: int
    align: AlignStageSettings
    splat: SplatStageSettings
    render: RenderStageSettings
    denoise: DenoiseStageSettings | None = None  # round 1
    select: SelectStageSettings | None = None  # rounds >= 2
    refine: RefineStageSettings | None = None  # rounds >= 2
    fuse: FuseStageSettings | None = None  # with `PipelineConfig.fuse_noisy_splat`


def _replace_given(cfg, **changes):
    """`cfg` with the non-None `changes` applied."""
    return dataclasses.replace(cfg, **{k: v for k, v in changes.items() if v is not None})


def n2v_config(settings: DenoiseSettings) -> N2VConfig:
    """Round 1's `N2VConfig`: the preset `settings.n2v_preset` with `n2v_steps` and `method` applied.

    `method="auto"` gives R2R's config: the objective is chosen from the photos in the denoise stage
    (`DenoiseStageSettings.choose_objective`); a caller that trains without the stage chooses it itself
    (`denoise.self_supervised.choose_objective`).

    Raises:
        ConfigError: unknown preset name.
    """
    from denoise.n2v import N2V_PRESETS  # torch: see the module docstring

    if settings.n2v_preset not in N2V_PRESETS:
        raise ConfigError(f"unknown N2V preset {settings.n2v_preset!r}", key="denoise.n2v_preset",
                          expected=" | ".join(N2V_PRESETS))
    method = "r2r" if settings.method == "auto" else settings.method  # "auto": chosen in the stage
    return _replace_given(N2V_PRESETS[settings.n2v_preset], steps=settings.n2v_steps, method=method)


def round2_config(settings: DenoiseSettings) -> Round2Config:
    """The refine stage's `Round2Config`: the defaults with `round2_steps` and, for "charbonnier",
    the loss replaced (the joint loss is `Round2Config`'s default).

    Raises:
        ConfigError: unknown preset name.
    """
    from denoise.round2 import Round2Config  # torch: see the module docstring

    if settings.round2_preset not in ROUND2_PRESETS:
        raise ConfigError(f"unknown round-2 preset {settings.round2_preset!r}", key="denoise.round2_preset",
                          expected=" | ".join(ROUND2_PRESETS))
    loss = None if settings.round2_loss == "joint" else settings.round2_loss
    return _replace_given(Round2Config(), steps=settings.round2_steps, loss=loss)


def align_config(settings: AlignSettings, *, seed: int) -> AlignConfig:
    """The align stage's `AlignConfig`: the preset with the non-None overrides and `seed`.

    Raises:
        ConfigError: unknown preset name.
    """
    from mvgeo.align import PREVIEW, AlignConfig  # torch: see the module docstring

    presets = {"default": AlignConfig(), "preview": PREVIEW}
    if settings.preset not in presets:
        raise ConfigError(f"unknown alignment preset {settings.preset!r}", key="align.preset",
                          expected=" | ".join(ALIGN_PRESETS))
    cfg = _replace_given(presets[settings.preset], seed=seed, max_size_px=settings.max_size_px,
                         points_budget=settings.points, max_focal_log_std=settings.max_focal_log_std)
    if settings.iters is not None:
        cfg = dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, iters=settings.iters))
    return cfg


def train_config(settings: SplatSettings, *, seed: int) -> TrainConfig:
    """The splat stage's `TrainConfig`: the preset `settings.preset` with `iters` and `seed`.

    Raises:
        ConfigError: unknown preset name.
    """
    from splat.train import TRAIN_PRESETS  # torch: see the module docstring

    if settings.preset not in TRAIN_PRESETS:
        raise ConfigError(f"unknown splat preset {settings.preset!r}", key="splat.preset",
                          expected=" | ".join(TRAIN_PRESETS))
    return _replace_given(TRAIN_PRESETS[settings.preset], iters=settings.iters, seed=seed)


def splat_stage_settings(config: PipelineConfig, *, seed: int) -> SplatStageSettings:
    """The splat stage's settings under `config` (its training configuration with `seed`, and the noisy
    photos' band in its target); the pipeline's rounds and `eval`'s true-camera splats use the same."""
    return SplatStageSettings(train_config(config.splat, seed=seed), config.device,
                              NoisyDetail(config.splat.noisy_detail, config.splat.noisy_detail_sigma_px))


def round_settings(config: PipelineConfig, round_index: int) -> RoundSettings:
    """The typed settings of round `round_index`'s stages under `config`.

    Raises:
        ConfigError: a preset name that its component does not have.
    """
    r, d = round_index, config.denoise

    def seed(stage: str) -> int:
        return stage_seed(config.seed, r, stage)

    from denoise.grouped_wiener import GroupedWienerConfig
    from denoise.wiener import WienerConfig  # scipy: resolved when called, as the component configs are

    later = r >= 2
    align = AlignStageSettings(align_config(config.align, seed=seed("align")),
                               reuse_intrinsics=config.align.reuse_intrinsics if later else None,
                               reuse_geometry=config.align.reuse_geometry if later else None,
                               photos="denoised" if later else config.align.photos)
    fuse = FuseStageSettings(train_config(config.splat, seed=seed("fuse")), config.device,
                             reuse_noisy_splat=config.reuse_noisy_splat if later else None) \
        if config.fuse_noisy_splat else None
    return RoundSettings(
        index=r, align=align, fuse=fuse,
        splat=splat_stage_settings(config, seed=seed("splat")),
        render=RenderStageSettings(config.device),
        denoise=None if later else DenoiseStageSettings(n2v_config(d), d.passes, config.device, d.keep_noisy,
                                                               choose_objective=d.method == "auto",
                                                               wiener=WienerConfig() if d.wiener else None,
                                                               grouped=GroupedWienerConfig(passes=d.grouped_wiener_passes)
                                                               if d.grouped_wiener
                                                               else None, pd_stride=d.pd_stride,
                                                               noise_model=d.noise_model,
                                                               pass_clean_below_255=d.pass_clean_below_255),
        select=SelectStageSettings(config.views, config.select_views) if later else None,
        refine=RefineStageSettings(round2_config(d), d.passes, config.device, d.pd_stride,
                                   d.noise_model) if later else None)


def check_settings(config: PipelineConfig) -> None:
    """Resolve every stage's settings of a run under `config` (rounds 1 and 2 cover every kind of
    stage) before any compute.

    Raises:
        ConfigError: a preset name that its component does not have.
    """
    for r in range(1, min(config.rounds, 2) + 1):
        round_settings(config, r)
