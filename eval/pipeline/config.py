"""Typed settings of the Denoise-GS pipeline, with the `fast`, `default` and `best` presets.

Component settings name a preset of the component's own config
(`denoise.N2VConfig`, `mvgeo.align.AlignConfig`, `splat.TrainConfig`, ...)
plus the few knobs the pipeline and the cost report sweep; `None` keeps the
component preset's value. Every field is part of the stage hashes, so
changing one re-runs the stages it affects and nothing else.
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass, field
from typing import Literal

from mvgeo.common.errors import ConfigError

__all__ = ["ALIGN_PHOTOS", "PASS_CLEAN_BELOW_255", "PRESETS", "AlignSettings", "DenoiseSettings", "PipelineConfig",
           "SplatSettings", "preset"]

Round2Loss = Literal["joint", "charbonnier"]
DenoiseMethod = Literal["n2v", "neighbor2neighbor", "r2r", "auto"]
#: The values of `DenoiseSettings.method`.
DENOISE_METHODS: tuple[str, ...] = ("n2v", "neighbor2neighbor", "r2r", "auto")
ReuseIntrinsics = Literal["auto", "always", "never"]
ReuseGeometry = Literal["auto", "never"]
#: The most passes of the grouped Wiener step a configuration may ask for (`DenoiseSettings.grouped_wiener_passes`).
MAX_GROUPED_WIENER_PASSES = 10

AlignPhotos = Literal["denoised", "noisy_first", "better_of"]
#: The values of `AlignSettings.photos`.
ALIGN_PHOTOS: tuple[str, ...] = ("denoised", "noisy_first", "better_of")
#: The presets' `DenoiseSettings.pass_clean_below_255`: over the levels clean photos read (0.5-1.0/255 on
#: DTU scan24 and the temple ring), under any noise worth a network (sigma 25/255 reads 23-26).
PASS_CLEAN_BELOW_255 = 1.5


@dataclass(frozen=True)
class DenoiseSettings:
    """N2V-UNet training (round 1), fine-tuning (rounds >= 2) and inference.

    Attributes:
        n2v_preset: name of a `denoise` N2V preset for round 1.
        method: round 1's self-supervised objective on the same UNet (`denoise.n2v.N2VConfig.method`):
            "n2v" (default, the paper's), "neighbor2neighbor", "r2r" (docs/bench/denoise_real.md), or
            "auto": R2R, or Neighbor2Neighbor where a large share of the noisy photos lies in dark
            clipped regions, where R2R's recorruption does not hold (`denoise.self_supervised.
            choose_objective`). Rounds >= 2 fine-tune a blind-spot network, so the others run with
            `rounds=1` only.
        n2v_steps: training steps; None keeps the preset's.
        passes: inference maskings averaged per image (the paper's K); 0 runs one pass on the
            unmasked image (`denoise.inference.denoise_images`).
        round2_preset: name of a `denoise` round-2 fine-tuning preset.
        round2_steps: fine-tuning steps; None keeps the preset's.
        round2_loss: "joint" (the paper's loss) or "charbonnier" (Table 2 ablation).
        keep_noisy: fraction k of the noisy photo kept in round 1's photos, ``(1 - k) * denoised +
            k * noisy`` (in ``[0, 1)``; 0: the denoiser's output). The splat averages independent noise
            across views but keeps a denoiser's blur, so photos with a little unbiased noise left can
            splat sharper (measured trade in docs/bench/pipeline.md, "the clipping bias undone").
        wiener: round 1's photos are the network's outputs refined by the sliding-window DCT Wiener step
            (`denoise.wiener`: the noisy photo shrunk by the gains each output implies; about half a second
            per 384 x 384 photo on one core). On DTU scan24 at sigma 25 it lifts R2R's photos 0.9 dB, on the
            temple ring Neighbor2Neighbor's 1.8 dB (docs/bench/denoise_real.md, "The DCT Wiener step").
        grouped_wiener: then the grouped Wiener step (`denoise.grouped_wiener`: similar 5 x 5 patches of the
            noisy photo filtered together with the covariance of the photo so far; about 1.5 s per 384 x 384
            photo on 2 cores, docs/bench/denoise_wiener_speed.md; docs/bench/denoise_real.md, "The grouped
            Wiener step").
        grouped_wiener_passes: with `grouped_wiener`, how many passes of it, each with the previous one's
            output as its pilot and 80 patches per group after the first (`GroupedWienerConfig.passes`).
        pd_stride: round 1 denoises pixel-shuffled sub-images of every `pd_stride`-th pixel
            (`denoise.pixel_shuffle`), for noise correlated between neighbouring pixels as a camera's
            demosaicing leaves it; 0 (default): the stride `denoise.pixel_shuffle.choose_stride` measures
            from the photos, 1 for independent noise (then nothing changes); 1: off; 2 to 4: that stride.
            Rounds >= 2 fine-tune and apply the network on the sub-images of the same stride.
        noise_model: how the denoisers read each photo's (or sub-image's) noise level
            (`denoise.inference.NoiseModel`); None (default): as `denoise.pixel_shuffle.choose_stride` finds
            the photos' noise (on the luma where it is chroma-subsampled, as a JPEG's; else on the colour
            patches, "auto"). "luma" reads the luma whatever was found: for a camera's JPEGs whose noise is
            too faint in the colour patches to be found (quality 80 and under, or a clipped black
            background; docs/bench/denoise_real.md), with `pd_stride` 2.
        pass_clean_below_255: round 1 passes the photos through undenoised, and trains no network, when every
            photo's noise level (as the denoiser reads it, /255) is under this and nothing hints at noise the
            level misses (`denoise.pixel_shuffle.NoiseLevels.hint`); a round 2 then does not run. Clean photos
            read 0.5-1.0/255 (DTU scan24 and the temple ring at 384-512 px), photos with sigma 25/255 added
            23-26; denoising clean photos changes them by nothing (50 dB from their input) in 31-49 % of the
            run (docs/bench/pipeline.md, "Photos without added noise"). 0: always denoise (the paper's).
    """

    n2v_preset: str = "default"
    method: DenoiseMethod = "n2v"
    n2v_steps: int | None = None
    passes: int = 8
    round2_preset: str = "default"
    round2_steps: int | None = None
    round2_loss: Round2Loss = "joint"
    keep_noisy: float = 0.0
    wiener: bool = False
    grouped_wiener: bool = False
    grouped_wiener_passes: int = 1
    pd_stride: int = 0
    noise_model: str | None = None
    pass_clean_below_255: float = 0.0


@dataclass(frozen=True)
class AlignSettings:
    """Pose-free alignment (`mvgeo.align`).

    Attributes:
        preset: "default" (`mvgeo.align.AlignConfig()`) or "preview" (`mvgeo.align.PREVIEW`).
        max_size_px: long side the images are downscaled to; None keeps the preset's.
        iters: global-alignment iterations; None keeps the preset's.
        points: output point budget (`mvgeo.align.AlignConfig.points_budget`), which is the number
            of Gaussians the splat starts from; None keeps the preset's.
        max_focal_log_std: `mvgeo.align.AlignConfig.max_focal_log_std` (alignment refuses when no
            pair determines the focal length and the bundle adjustment leaves a larger relative
            uncertainty); None keeps the preset's (strict). The evaluation sets it very large:
            InstantSplat-style methods then keep the focal they estimate (or the prior), and the
            held-out scores and pose errors measure what that costs.
        reuse_intrinsics: rounds >= 2 only (round 1's stage keys ignore it): "auto" keeps the
            better-determined of this round's focal estimate and the previous round's (the
            bundle adjustment's `focal_log_std`), re-aligning with the previous calibration fixed
            when that one wins or when this round's views do not determine the focal; "always"
            uses the previous round's calibration; "never" estimates anew every round (the
            paper's loop). See `eval.pipeline.calibration`.
        reuse_geometry: rounds >= 2 only (round 1's stage keys ignore it): "auto" hands the previous
            round's poses, intrinsics and points (for this round's views) to this round's splat when the
            previous alignment determines those views' camera centres better (bundle-adjustment
            uncertainty, no ground truth), when this round registers fewer of them, or when this
            round's alignment fails; "never" uses this round's own alignment (the paper's loop). See
            `eval.pipeline.calibration.choose_geometry`.
        photos: round 1's alignment input: "denoised" (the paper's: the denoised photos) or "noisy_first"
            (the noisy photos, and the denoised ones only where the noisy ones are refused). The splat
            trains on the denoised photos either way. On DTU scan24 at sigma 25 the noisy photos align
            at 0.32 deg against 0.45 for N2V's photos, and R2R's 29.5 dB photos were refused (one view's
            matches contradicted: the clean-photo feature detector, chosen by their low noise, finds
            features in the denoiser's texture); at sigma 50 the noisy photos were refused and N2V's
            aligned, until views cut off by contradicted pairs were located by PnP (`mvgeo.align.locate`):
            they align at 0.91 deg now (docs/bench/pipeline.md). After the noisy photos, the denoised ones
            are matched with the noisy photos' detector (`eval.pipeline.align_stage.denoised_photos_config`):
            R2R's photos at sigma 50 align so (1.1 deg) and were refused with the clean-photo one. "better_of"
            aligns both (the denoised ones with the noisy photos' detector) and keeps the alignment whose camera centres
            the bundle adjustment determines better (`eval.pipeline.calibration.better_determined`; either one
            where the other is refused). Rounds >= 2 align the round's denoised photos.
        intrinsics: the photos' calibration at their input size (a COLMAP cameras.txt with one camera, or
            an mrcal .cameramodel), without lens distortion (the splat trains on the photos as they are);
            None: estimated. Every round's alignment uses it instead of estimating the focal length
            (`mvgeo align --intrinsics`); its content and file name, not its folder, enter the align stages'
            keys.
    """

    preset: str = "default"
    max_size_px: int | None = None
    iters: int | None = None
    points: int | None = None
    max_focal_log_std: float | None = None
    reuse_intrinsics: ReuseIntrinsics = "auto"
    reuse_geometry: ReuseGeometry = "auto"
    photos: AlignPhotos = "denoised"
    intrinsics: str | None = None


@dataclass(frozen=True)
class SplatSettings:
    """Gaussian splatting with pose optimisation (`splat`).

    Attributes:
        preset: name of a `splat.train.TRAIN_PRESETS` entry ("instantsplat", "quick", ...).
        iters: training iterations; None keeps the preset's.
        noisy_detail: extension, not in the paper: the fraction ``w`` of the noisy photo's finest band
            that the splat's target takes back, ``denoised + w * highpass(noisy - denoised)``
            (`denoise.detail.noisy_detail_target`; 0 = off, the paper's target). The denoiser's texture
            differs from view to view and the splat averages it into a blur; the noisy photo's texture is
            the same in every view and its noise is not, so the splat keeps the one and averages the other.
            Above a noise std of 25/255 (the denoiser's estimate) the weight is scaled by (25/255) / sigma,
            so the noise it adds stays at ``w * 25/255`` (`denoise.detail.noisy_detail_weight`); dark clipped
            regions (a black background, whose band is rectified noise) get none of it. Costs a blur
            and a noise estimate per photo. docs/bench/pipeline.md, "The noisy photos' finest band in the
            splat's target".
        noisy_detail_sigma_px: the band's Gaussian, standard deviation in pixels at the working size.
    """

    preset: str = "instantsplat"
    iters: int | None = None
    noisy_detail: float = 0.0
    noisy_detail_sigma_px: float = 1.0


@dataclass(frozen=True)
class PipelineConfig:
    """The whole `denoise-gs run`.

    Attributes:
        views: K, the number of views kept for rounds >= 2 (k-means clusters
            over camera poses; the sharpest image of each cluster).
        rounds: 1 = round 1 only; N > 1 repeats the second round N - 1 times.
        seed: master seed; each stage derives its own from (seed, round, stage).
        select_views: False = rounds >= 2 use every view (Table 2 ablation).
        fuse_noisy_splat: extension, not in the paper: each round's splat trains on the average of the
            denoised photo and the render, at its view, of a splat trained on the *noisy* photos with
            the same alignment (`eval.pipeline.fuse_stage.fuse`). The two estimates of the clean image err
            differently (the denoiser removes fine texture; the splat of the noisy photos keeps it and
            averages the noise across views), so their mean is better than either. Costs one more
            splat training per round. On the scenes measured it raised the held-out PSNR and lowered the
            LPIPS of the paper's loop (docs/bench/pipeline.md, docs/bench/pipeline_demo.md); the noisy
            photos' finest band in the splat's target (`SplatSettings.noisy_detail`) does more for less
            and replaced it in every preset. `denoise-gs eval`'s `n2v_round1` and `denoise_gs` keep the
            paper's loop (off); `n2v_fused_round1` and `denoise_gs_fused` turn it on.
        reuse_noisy_splat: with `fuse_noisy_splat`, rounds >= 2 only (round 1's stage keys ignore it):
            when the round's alignment of its views is the previous round's (cameras and cam_from_world
            equal up to float64 round-off, the same points; `AlignSettings.reuse_geometry` hands it
            over) and its noisy photos are the same, the fuse stage takes the previous round's renders
            of the noisy-photo splat for its views instead of training a new one on a subset of the
            same photos with the same start (the previous splat saw these views and more). Saves one
            splat training per such round; False trains every round (`eval.pipeline.fuse_stage.fuse`,
            docs/bench/pipeline_schedule.md).
        stop_when_unrefined: rounds >= 2: when a round's refine keeps the previous round's network
            (round 2's blind-spot-loss guard, `denoise.round2.refine_round2`, found the fine-tuned one no
            better), the loop stops after that stage and the previous round's reconstruction is the
            result: the round would only align and splat again a subset (K views) of the previous
            round's own photos. The guard reverts on most scenes measured, where the re-splat scored
            below round 1 (docs/bench/pipeline_schedule.md, section 4). False runs every round
            whatever the guard says (the paper's loop; `denoise-gs eval`'s `denoise_gs`, `rounds_N`).
        device: torch device for the networks and the splatting ("cpu", "cuda").
        max_size: long side in pixels of the working images (`--max-size`): larger inputs are
            downscaled once, with the area filter, before any stage (`eval.pipeline.inputs`);
            None works at the input size. 512 is InstantSplat's working size.
        denoise, align, splat: component settings.
    """

    views: int = 12
    rounds: int = 2
    seed: int = 0
    select_views: bool = True
    fuse_noisy_splat: bool = False
    reuse_noisy_splat: bool = True
    stop_when_unrefined: bool = False
    device: str = "cpu"
    max_size: int | None = 512
    denoise: DenoiseSettings = field(default_factory=DenoiseSettings)
    align: AlignSettings = field(default_factory=AlignSettings)
    splat: SplatSettings = field(default_factory=SplatSettings)

    def __post_init__(self) -> None:
        if self.views < 2:
            raise ConfigError(f"must be at least 2, got {self.views}", key="views", expected="an integer >= 2")
        if self.rounds < 1:
            raise ConfigError(f"must be at least 1, got {self.rounds}", key="rounds", expected="an integer >= 1")
        if self.denoise.passes < 0:
            raise ConfigError(f"must be at least 0, got {self.denoise.passes}", key="denoise.passes",
                              expected="an integer >= 0 (0: one pass on the unmasked image)")
        if self.denoise.method not in DENOISE_METHODS:
            raise ConfigError(f"unknown method {self.denoise.method!r}", key="denoise.method",
                              expected=" or ".join(map(repr, DENOISE_METHODS)))
        if self.denoise.method != "n2v" and self.rounds >= 2:
            raise ConfigError(f"{self.denoise.method} runs round 1 only: round 2 fine-tunes a blind-spot (N2V) "
                              f"network", key="denoise.method",
                              fix="use --rounds 1, or the N2V denoiser (`--denoiser n2v`, or `--preset fast`)")
        if not 0.0 <= self.denoise.keep_noisy < 1.0:
            raise ConfigError(f"must be in [0, 1), got {self.denoise.keep_noisy}", key="denoise.keep_noisy",
                              expected="a fraction of the noisy photo, 0 <= k < 1")
        passes = self.denoise.grouped_wiener_passes
        if (isinstance(passes, bool) or not isinstance(passes, numbers.Integral) or
                not 1 <= passes <= MAX_GROUPED_WIENER_PASSES):
            raise ConfigError(f"must be an integer in [1, {MAX_GROUPED_WIENER_PASSES}], got {passes!r}",
                              key="denoise.grouped_wiener_passes",
                              expected=f"1 (one pass) to {MAX_GROUPED_WIENER_PASSES} (each pass takes about as long "
                                       "as the first; the second gains 0.14-0.28 dB)")
        from denoise.pixel_shuffle import MAX_STRIDE

        stride = self.denoise.pd_stride
        if isinstance(stride, bool) or not isinstance(stride, numbers.Integral) or not 0 <= stride <= MAX_STRIDE:
            raise ConfigError(f"must be an integer from 0 to {MAX_STRIDE}, got {stride!r}",
                              key="denoise.pd_stride", expected="0 (measured from the photos), 1 (off) or a stride")
        from denoise.inference import NOISE_MODELS

        if self.denoise.noise_model is not None and self.denoise.noise_model not in NOISE_MODELS:
            raise ConfigError(f"unknown noise model {self.denoise.noise_model!r}", key="denoise.noise_model",
                              expected=f"one of {', '.join(NOISE_MODELS)}, or none (measured from the photos)")
        level = self.denoise.pass_clean_below_255
        if isinstance(level, bool) or not isinstance(level, numbers.Real) or not 0.0 <= level < 255.0:
            raise ConfigError(f"must be a number from 0 to 255, got {level!r}", key="denoise.pass_clean_below_255",
                              expected="a noise level /255 such as 1.5, or 0 (always denoise)")
        if self.denoise.round2_loss not in ("joint", "charbonnier"):
            raise ConfigError(f"unknown loss {self.denoise.round2_loss!r}", key="denoise.round2_loss",
                              expected="'joint' or 'charbonnier'")
        if self.align.reuse_intrinsics not in ("auto", "always", "never"):
            raise ConfigError(f"unknown value {self.align.reuse_intrinsics!r}", key="align.reuse_intrinsics",
                              expected="'auto', 'always' or 'never'")
        if self.align.photos not in ALIGN_PHOTOS:
            raise ConfigError(f"unknown value {self.align.photos!r}", key="align.photos",
                              expected="'denoised', 'noisy_first' or 'better_of'")
        if self.align.reuse_geometry not in ("auto", "never"):
            raise ConfigError(f"unknown value {self.align.reuse_geometry!r}", key="align.reuse_geometry",
                              expected="'auto' or 'never'")
        if self.max_size is not None and self.max_size < 32:  # validate.MIN_IMAGE_SIZE_PX
            raise ConfigError(f"must be at least 32 px, got {self.max_size}", key="max_size",
                              expected="an integer >= 32, or None for the input size")
        for key, value in (("denoise.n2v_steps", self.denoise.n2v_steps),
                           ("denoise.round2_steps", self.denoise.round2_steps),
                           ("align.max_size_px", self.align.max_size_px), ("align.iters", self.align.iters),
                           ("align.points", self.align.points),
                           ("splat.iters", self.splat.iters)):
            if value is not None and value < 1:
                raise ConfigError(f"must be positive, got {value}", key=key)
        if not 0.0 <= self.splat.noisy_detail <= 1.0:
            raise ConfigError(f"must be in [0, 1], got {self.splat.noisy_detail}", key="splat.noisy_detail",
                              expected="a fraction of the noisy photo's finest band, 0 <= w <= 1 (0: off)")
        if not self.splat.noisy_detail_sigma_px > 0.0:
            raise ConfigError(f"must be positive, got {self.splat.noisy_detail_sigma_px}",
                              key="splat.noisy_detail_sigma_px", expected="a blur in pixels > 0")

    def to_dict(self) -> dict:
        """Plain JSON-able dict (for hashing and report.json)."""
        return dataclasses.asdict(self)


#: Named presets; held-out figures and end-to-end times are in docs/bench/pipeline.md (`default`,
#: `best`, three seeds) and docs/bench/pipeline_demo.md (`fast`, `make demo`).
#:
#: - `fast`: what `make demo` and the tests run, minutes on 2 CPU cores: one round of N2V's short preset
#:   with 2 inference passes (with `--rounds 2`, 40 round-2 fine-tuning steps and the stop when the refine
#:   keeps the previous network; round 2 lowered DTU scan24 with Poisson-Gaussian noise by 1.07 dB held
#:   out, docs/bench/pipeline_demo.md), the preview alignment with every point kept
#:   (up to 100k), the `instantsplat` splat (1000 iterations; with the 300 of `quick` the demo's denoised
#:   views were +1.12 dB over the noisy splat's, with 1000 +1.67); round 1's photos refined by the DCT
#:   Wiener step (on `make demo`'s scene 25.08 / 0.744 / 0.131 held out against 24.86 / 0.734 / 0.145
#:   without it); the splat trains on the denoised photos plus 0.5 of the noisy photos' finest band
#:   (`SplatSettings.noisy_detail`, scaled down above sigma 25/255), without which N2V's novel views are
#:   blurrier than those of a splat of the noisy photos. The band replaced the noisy-photo fusion
#:   (`fuse_noisy_splat`, one more splat training per round): seed 0, held out, band against fusion, `make
#:   demo`'s scene 25.13 / 0.746 / 0.129 against 25.08 / 0.744 / 0.131 with 116 s of stages against 196 s;
#:   DTU scan24 at sigma 25 24.53 / 0.750 / 0.153 against 24.28 / 0.700 / 0.195, 242 s against 391 s
#:   (docs/bench/pipeline_demo.md, "The noisy band instead of the fusion in `fast`").
#: - `default`: round 1 only, with the UNet trained by Recorrupted-to-Recorrupted for 2000 steps instead
#:   of N2V's 400, its photos refined by the DCT Wiener step (`DenoiseSettings.wiener`: on DTU scan24 at
#:   sigma 25, 25.16 / 0.809 / 0.149 held out against 25.04 / 0.798 / 0.162 without it, three seeds; with
#:   Poisson-Gaussian noise SSIM and LPIPS better, PSNR 0.14 dB lower; docs/bench/pipeline.md, "The DCT
#:   Wiener step"), then by the grouped Wiener step (`DenoiseSettings.grouped_wiener`: on DTU scan24 at sigma
#:   25, 25.18 / 0.818 / 0.133 held out against 25.07 / 0.808 / 0.149 without it, three seeds; docs/bench/
#:   pipeline.md, "The grouped Wiener step through the splat"); no fusion; round 1 aligns the noisy photos
#:   and the denoised ones and keeps the alignment whose camera centres are better determined
#:   (`AlignSettings.photos="better_of"`: on DTU scan24 at sigma 25 the denoised photos' on every seed, held
#:   out 25.59 / 0.824 / 0.128 against 25.32 / 0.819 / 0.130 with the noisy photos' alone, three seeds;
#:   docs/bench/pipeline.md, "Round 1 keeps the better-determined of two alignments"); the splat trains on
#:   the denoised photos plus 0.2 of the noisy photos' finest band (`SplatSettings.noisy_detail`, scaled down
#:   above sigma 25/255; docs/bench/pipeline.md, "The noisy photos' finest band in the splat's target"), for
#:   2000 iterations, twice InstantSplat's (the denoised photos carry little noise for the longer fit to
#:   learn, and at 1000 a splat of 12 views at 384 x 384 is not converged: on DTU scan24 at sigma 25, three
#:   seeds, 25.67 / 0.833 / 0.085 held out against 25.56 / 0.825 / 0.109, every seed better, for twice the
#:   splat's time; the noisy photos' splat loses 0.7 dB from the same, so `denoise-gs eval`'s baselines
#:   keep 1000; docs/bench/pipeline.md, "The product's splat for 2000 iterations"; on the temple ring's
#:   30-degree ring with the true cameras the longer fit loses 0.54 dB, SSIM 0.013, for LPIPS -0.004, seed 0,
#:   "The temple ring with the true cameras at 1000 and 2000 iterations"). On DTU
#:   scan24 (sigma 25/255) its photos are 29.5 dB against N2V's 25.8, and splatted with the true cameras
#:   they score 24.93 / 0.806 / 0.134 against the N2V two-round product's 24.41 / 0.732 / 0.198 (PSNR /
#:   SSIM / LPIPS); fusing them with the noisy splat's render costs 0.4 dB and 0.07 SSIM there, and round
#:   2 fine-tunes a blind-spot network only, so a non-blind denoiser runs one round (docs/bench/pipeline.md,
#:   "the default denoiser"). Photos with large black clipped regions (more than a fifth of their area)
#:   train Neighbor2Neighbor instead (`DenoiseSettings.method="auto"`): on the temple ring's black
#:   background R2R's recorruption does not hold (its photos 27.1 dB against 34.3). The paper's loop is
#:   `--denoiser n2v --rounds 2` (`denoise-gs eval`'s `denoise_gs`, `denoise_gs_fused`).
#: - `best`: the `default` (both Wiener steps and the 2000-iteration splat included: the DCT step lifts
#:   `best`'s photos 0.67 dB on DTU scan24; `best`'s held-out figures below predate both Wiener steps) with
#:   the UNet at width 32 (`denoise.n2v.N2V_PRESETS["wide"]`, 2.3-2.6x the denoiser's CPU time per
#:   training step; every method that trains the UNet under `best` trains it at width 32). Measured before
#:   the Wiener steps, on DTU scan24 at sigma 25: the longer splat alone, three seeds, 25.06 / 0.792 / 0.152
#:   against 24.87 / 0.792 / 0.166 held out; with the wider UNet, seed 0: 25.36 / 0.804 / 0.135 against
#:   25.13 / 0.794 / 0.154 (its photos 31.13 dB / 0.856 SSIM against 30.52 / 0.837; docs/bench/pipeline.md);
#:   on `llff_like` a 2000-iteration splat after N2V gained nothing.
#:
#: With rounds >= 2, all three keep the better-determined focal length and poses across rounds
#: (`AlignSettings.reuse_intrinsics`, `reuse_geometry`) and, when a round keeps the previous round's
#: poses, the previous round's noisy-photo splat (`reuse_noisy_splat`; docs/bench/pipeline_schedule.md),
#: and stop after a round whose refine kept the previous network (`stop_when_unrefined`).
#:
#: All three pass photos that read as clean through round 1 undenoised (`DenoiseSettings.
#: pass_clean_below_255` = `PASS_CLEAN_BELOW_255`).
_ONE_ROUND = PipelineConfig(rounds=1, stop_when_unrefined=True,
                            denoise=DenoiseSettings(method="auto", n2v_steps=2000, wiener=True, grouped_wiener=True,
                                                    pass_clean_below_255=PASS_CLEAN_BELOW_255),
                            align=AlignSettings(photos="better_of"), splat=SplatSettings(iters=2000, noisy_detail=0.2))
PRESETS: dict[str, PipelineConfig] = {
    "fast": PipelineConfig(
        rounds=1, stop_when_unrefined=True,
        denoise=DenoiseSettings(n2v_preset="fast", passes=2, round2_steps=40, wiener=True,
                                pass_clean_below_255=PASS_CLEAN_BELOW_255),
        # PREVIEW thins its cloud to 20k points; at 256x192 and 12 views the splat started from
        # every point (~60k) scored +0.5 dB / LPIPS -0.09..-0.17 held out for 15-40 % more splat time
        # (docs/bench/pipeline.md, "the splat's point budget").
        align=AlignSettings(preset="preview", points=100_000),
        # The `instantsplat` splat (1000 iterations), as `default`'s: on `make demo`'s scene the noisy
        # photos' splat gains nothing from it over 300 (23.30 -> 23.23 dB) and the denoised ones +0.47 dB,
        # LPIPS -0.13 (docs/bench/pipeline_demo.md, "the splat's length").
        splat=SplatSettings(noisy_detail=0.5),
    ),
    "default": _ONE_ROUND,
    "best": dataclasses.replace(_ONE_ROUND, denoise=dataclasses.replace(_ONE_ROUND.denoise, n2v_preset="wide")),
}


def preset(name: str, *, views: int | None = None, rounds: int | None = None, seed: int | None = None,
           select_views: bool | None = None, device: str | None = None) -> PipelineConfig:
    """Preset `name` with the given top-level fields replaced (None keeps the preset's).

    Raises:
        ConfigError: unknown preset name or an invalid value.
    """
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}", key="preset", expected=" | ".join(PRESETS))
    given = {"views": views, "rounds": rounds, "seed": seed, "select_views": select_views, "device": device}
    return dataclasses.replace(PRESETS[name], **{k: v for k, v in given.items() if v is not None})
