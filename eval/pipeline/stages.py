"""The product's stage functions: Denoise-GS's steps as disk-in, disk-out functions.

Each function has the `StageFn` signature (`fn(ctx) -> summary`), reads
`ctx.inputs`, writes the outputs `eval.pipeline.run` declares for it into
`ctx.work_dir`, and runs the component packages with the typed settings it
receives (`ctx.settings`, `eval.pipeline.stage_settings`).

The component packages (`denoise`, `splat`, `mvgeo.align`) load torch, so each
function imports what it calls when it runs, not when this module is imported.

The align and fuse stages are defined in `eval.pipeline.align_stage` and `eval.pipeline.fuse_stage`,
the splat training the splat and fuse stages share in `eval.pipeline.splat_training`; `product_stages`
gathers them all.

| stage     | inputs                                   | outputs                                   |
|-----------|------------------------------------------|-------------------------------------------|
| denoise   | noisy                                    | denoised/, n2v_model.pt                   |
| align     | images [, previous_align (rounds >= 2)]  | align/ (sparse/0/, points.ply/.npz, json) |
| fuse      | noisy, images, align [, previous_*]      | fused/, noisy_renders/                    |
| splat     | images (or fused), align                 | sparse/0/, point_cloud.ply                |
| render    | sparse, scene                            | renders/                                  |
| select    | images, sparse                           | selection.json                            |
| refine    | noisy, selection, model, renders, previous | denoised/, n2v_model.pt                 |
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eval.pipeline.align_stage import align
from eval.pipeline.fuse_stage import fuse
from eval.pipeline.splat_training import train_splat
from eval.pipeline.stage import StageContext, StageFn
from eval.pipeline.stage_settings import SplatStageSettings
from eval.pipeline.summaries import (
    DenoiseSummary,
    NoisyDetailRecord,
    RefineSummary,
    SelectionFile,
    SelectSummary,
    SplatSummary,
    history_ends,
)
from eval.pipeline.views import read_views, write_views
from mvgeo.sparse_model import PosedImage, SparseModel, read_sparse_model, write_sparse_model

__all__ = ["DENOISE_OUTPUTS", "MODEL_FILE", "PASS_THROUGH_UNWRITTEN", "STAGE_CODE", "PipelineStages", "denoise",
           "product_stages", "refine", "render", "select", "splat"]

_log = logging.getLogger(__name__)

#: The network a denoise or refine stage writes (round r >= 2 fine-tunes round r-1's).
MODEL_FILE = "n2v_model.pt"
#: What the product's denoise stage writes; a denoiser without a network (the evaluation's
#: baselines) writes "denoised" alone and runs round 1 only.
DENOISE_OUTPUTS = ("denoised", MODEL_FILE)
#: The outputs the denoise stage leaves unwritten when it passes photos that read as clean through
#: (`DenoiseStageSettings.pass_clean_below_255`): no network is trained, so a round 2 is not run.
PASS_THROUGH_UNWRITTEN = frozenset({MODEL_FILE})


@dataclass(frozen=True)
class PipelineStages:
    """The stage functions `run_pipeline` calls; tests pass small real ones."""

    denoise: StageFn
    align: StageFn
    splat: StageFn
    render: StageFn
    select: StageFn
    refine: StageFn
    fuse: StageFn | None = None  # `PipelineConfig.fuse_noisy_splat`; required only when that is on
    #: OUT/scene.splat, view/, cameras/ from the last round (`eval.pipeline.publish`); None skips it.
    export: StageFn | None = None
    #: stage name -> modules/packages it runs besides its function's own module (`StageSpec.code`).
    code: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    #: What `denoise` writes into the round folder: `DENOISE_OUTPUTS`, or ("denoised",) for a
    #: denoiser without a network, which cannot start a round 2 (no `MODEL_FILE` to fine-tune).
    denoise_outputs: tuple[str, ...] = DENOISE_OUTPUTS
    #: Files or folders outside the run that `denoise` reads besides the working photos, by their name in
    #: `ctx.inputs`; their contents enter its key (`StageSpec.hashed_inputs`), so a changed one re-runs it
    #: (`oracle_clean`'s clean photos). "noisy" is the working photos' name and may not be used.
    denoise_inputs: Mapping[str, Path] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if "noisy" in self.denoise_inputs:
            raise ValueError("denoise_inputs may not name an input 'noisy': the working photos have that name")


def denoise(ctx: StageContext) -> Mapping[str, object]:
    """Round 1: train the UNet on all noisy images with `n2v.method` (with `choose_objective`, the one
    `denoise.self_supervised.choose_objective` picks for them, recorded in the summary as `objective`),
    denoise them all (`ctx.settings`: `DenoiseStageSettings`); with `keep_noisy` k, `denoised/` holds
    ``(1 - k) * network output + k * noisy photo``. Where the photos' noise is correlated between
    neighbouring pixels (`pd_stride` 0: `denoise.pixel_shuffle.choose_stride` measures it) all of this runs
    on their pixel-shuffled sub-images, put back together after (`denoise.pixel_shuffle`). Where every
    photo's noise level reads under `pass_clean_below_255` and nothing hints at noise the level misses
    (`NoiseLevels.hint`), the photos are written as they are and no network is trained (`MODEL_FILE`
    unwritten, `passed_through` in the summary). Returns a `DenoiseSummary`'s JSON."""
    from denoise.model import save_checkpoint
    from denoise.parallel import one_thread_per_task
    from denoise.pixel_shuffle import merge_std, shuffled, stride_for, unshuffled
    from denoise.self_supervised import choose_objective, r2r_noise_std
    from eval.pipeline.quality import noise_level_255, noise_levels

    s = ctx.settings
    noisy = read_views(ctx.inputs["noisy"])
    photos = list(noisy.values())
    n2v, objective, dark_clipped_fraction = s.n2v, None, None
    if s.choose_objective:  # on the whole photos: the dark fraction's blur is in pixels of the photo
        choice = choose_objective(photos)
        n2v = dataclasses.replace(n2v, method=choice.method)
        objective, dark_clipped_fraction = choice.method, round(choice.dark_clipped_fraction, 4)
    levels = stride_for(photos, s.pd_stride, hint=s.noise_model is None)
    stride = levels.stride
    if stride > 1:
        _log.info("the photos' noise is correlated between neighbouring pixels (its level /255 by stride: %s): "
                  "denoising their %d x %d pixel-shuffled sub-images",
                  levels.levels_255(), stride, stride)
        photos = shuffled(photos, stride)
    if levels.hint() is not None and s.noise_model is None:
        _log.warning("%s", levels.hint())
    if levels.luma_level is not None:
        _log.info("the photos' colour patches read %.1f/255 of noise, their luma %.1f/255: chroma-subsampled noise, "
                  "as a JPEG's; its level is read on the luma", 255.0 * levels.level_by_stride[1],
                  255.0 * levels.luma_level)
    noise_model = s.noise_model or levels.noise_model
    # Each photo's noise std, estimated once: R2R's recorruption and both networks' clipping correction use
    # it, the report records it (N2V's fusion estimates its own), and it decides the pass-through.
    with one_thread_per_task():
        stds = [r2r_noise_std(im, noise_model=noise_model) for im in photos]
    passed = _reads_clean(stds, s.pass_clean_below_255) and levels.hint() is None
    model = None
    if passed:
        _log.info("every photo's noise level reads under %.1f/255 (at most %.2f/255): the photos are passed through "
                  "undenoised and no network is trained (`pass_clean_below_255`, `--pass-clean-below 0` to "
                  "denoise them anyway)", s.pass_clean_below_255, max(noise_level_255(v) for v in stds))
        out = list(photos)
    else:
        out, model = _denoise_photos(photos, n2v, s, ctx.seed, noise_model, stds)
    if stride > 1:
        n = stride * stride
        out = unshuffled(out, stride, [im.shape for im in noisy.values()])
        stds = [merge_std(stds[i * n:(i + 1) * n], stride, im.shape) for i, im in enumerate(noisy.values())]
    if s.keep_noisy > 0 and not passed:
        out = [(1.0 - s.keep_noisy) * d + s.keep_noisy * y for d, y in zip(out, noisy.values(), strict=True)]
    write_views(ctx.work_dir / "denoised", dict(zip(noisy, out, strict=True)))
    if model is not None:
        save_checkpoint(ctx.work_dir / MODEL_FILE, model)
    return DenoiseSummary(views=list(noisy), train=None if model is None else history_ends(model.history),
                          objective=objective, dark_clipped_fraction=dark_clipped_fraction,
                          training_restarts=[] if model is None else list(model.restarts),  # a diverged training
                          pd_stride=stride, noise_level_by_stride_255=levels.levels_by_stride_255() or None,
                          noise_level_luma_255=None if levels.luma_level is None else
                          round(255.0 * levels.luma_level, 2),
                          noise_level_luma_hint_255=None if levels.luma_hint_level is None or s.noise_model else
                          round(255.0 * levels.luma_hint_level, 2),
                          passed_through=passed or None,
                          noise=noise_levels(noisy, stds)).to_json()  # the report's noise level


def _reads_clean(stds: Sequence, below_255: float) -> bool:
    """Whether every photo's noise level (`eval.pipeline.quality.noise_level_255`, as the report reads it) is
    under `below_255`/255 (never, for 0)."""
    from eval.pipeline.quality import noise_level_255

    return below_255 > 0 and all(noise_level_255(v) < below_255 for v in stds)


def _denoise_photos(photos: list[np.ndarray], n2v, s, seed: int, noise_model: str, stds: list):
    """(denoised photos, the trained model): the denoise stage's network and steps; `noise_model`
    (`denoise.pixel_shuffle.NoiseLevels.noise_model`) read each photo's noise std in `stds`."""
    from denoise.parallel import one_thread_per_task
    from denoise.self_supervised import denoise_with_method, train_with_method

    # One torch thread per task for training and inference alike (`denoise.parallel`): the UNet's outputs
    # differ in the last float bits between thread counts, enough to flip a PNG level now and then.
    with one_thread_per_task():
        given = None if n2v.method == "n2v" else stds
        model = train_with_method(photos, n2v, seed=seed, device=s.device, noise_sigma=given,
                                  noise_model=noise_model)
        out = denoise_with_method(model, photos, n2v, passes=s.passes, seed=seed, noise_sigma=given,
                                  noise_model=noise_model, wiener=s.wiener, grouped=s.grouped)
    return out, model


def splat(ctx: StageContext) -> Mapping[str, object]:
    """Gaussian splatting with pose optimisation, initialised from the alignment (`ctx.settings`:
    `SplatStageSettings`). With `noisy_detail.weight > 0` the runner also passes the noisy working photos
    (`ctx.inputs["noisy"]`), whose finest band the targets take back (`PipelineConfig.splat.noisy_detail`).
    Returns a `SplatSummary`'s JSON."""
    from splat.ply import write_gaussian_ply

    s: SplatStageSettings = ctx.settings
    noisy = None
    if s.noisy_detail.weight > 0:
        if "noisy" not in ctx.inputs:
            raise ValueError("splat: noisy_detail is on but the runner passed no noisy photos (inputs['noisy'])")
        noisy = ctx.inputs["noisy"]
    res, sparse, stems, weights = train_splat(ctx.inputs["images"], ctx.inputs["align"], s, noisy)
    write_gaussian_ply(ctx.work_dir / "point_cloud.ply", res.model)
    optimised = [PosedImage(im.name, im.camera_id, np.asarray(res.cam_from_world_optimized[i])[:3])
                 for i, im in enumerate(sparse.images)]
    write_sparse_model(ctx.work_dir / "sparse" / "0",
                       SparseModel(sparse.cameras, optimised, sparse.points_xyz, sparse.points_rgb), binary=True)
    history = dataclasses.asdict(res.history) if dataclasses.is_dataclass(res.history) else res.history
    detail = NoisyDetailRecord(s.noisy_detail, weights) if weights is not None else None
    return SplatSummary(views=stems, train=history_ends(history), noisy_detail=detail,
                        timings_s=dict(res.timings_s)).to_json()


def render(ctx: StageContext) -> Mapping[str, object]:
    """Render the trained Gaussians at every pose of the round's `sparse/0` (`ctx.settings`:
    `RenderStageSettings`)."""
    from splat.ply import read_gaussian_ply
    from splat.render import render_views

    sparse = read_sparse_model(ctx.inputs["sparse"] / "0")
    model = read_gaussian_ply(ctx.inputs["scene"], device=ctx.settings.device)
    cameras = [sparse.camera_of(n) for n in sparse.names]
    cam_from_world = np.stack([sparse.image(n).cam_from_world for n in sparse.names])
    images = render_views(model, cameras, cam_from_world)
    stems = [n.rsplit(".", 1)[0] for n in sparse.names]
    write_views(ctx.work_dir / "renders", dict(zip(stems, images, strict=True)))
    return {"views": stems}


def select(ctx: StageContext) -> Mapping[str, object]:
    """Views for the next round: pose k-means (K = views) + sharpest (Laplacian variance) per cluster
    (`ctx.settings`: `SelectStageSettings`), in selection.json; returns a `SelectSummary`'s JSON."""
    s = ctx.settings
    sparse = read_sparse_model(ctx.inputs["sparse"] / "0")
    stems = [n.rsplit(".", 1)[0] for n in sparse.names]
    if not s.select_views or len(stems) <= s.views:
        selection = SelectionFile(stems, "all" if not s.select_views else "all (N <= K)")
    else:
        from denoise.view_selection import select_views

        images = read_views(ctx.inputs["images"], stems)
        cfw = {stem: sparse.image(n).cam_from_world for stem, n in zip(stems, sparse.names, strict=True)}
        sel = select_views(cfw, images, s.views, seed=ctx.seed)
        selection = SelectionFile(list(sel.names), "kmeans+laplacian",
                                  cluster_of={k: int(v) for k, v in dict(sel.cluster_of).items()},
                                  laplacian_var={k: float(v) for k, v in dict(sel.laplacian_var).items()})
    selection.write(ctx.work_dir / "selection.json")
    return SelectSummary(selected=list(selection.names), method=selection.method).to_json()


def refine(ctx: StageContext) -> Mapping[str, object]:
    """Rounds >= 2: fine-tune the UNet against the previous renders on the selected views, denoise them
    (`ctx.settings`: `RefineStageSettings`). Where the photos' noise is correlated between neighbouring
    pixels, as in round 1 (`denoise`), the photos and the renders are pixel-shuffled alike and the network
    fine-tuned and applied on the sub-images it learned on. Returns a `RefineSummary`'s JSON."""
    from denoise.inference import denoise_images
    from denoise.model import load_checkpoint, save_checkpoint
    from denoise.parallel import one_thread_per_task
    from denoise.pixel_shuffle import shuffled, stride_for, unshuffled
    from denoise.round2 import refine_round2

    s = ctx.settings
    names = SelectionFile.read(ctx.inputs["selection"]).names
    noisy = read_views(ctx.inputs["noisy"], names)
    renders = read_views(ctx.inputs["renders"], names)
    model = load_checkpoint(ctx.inputs["model"], device=s.device)
    levels = stride_for(list(noisy.values()), s.pd_stride, hint=False)  # round 1 reported any hint
    stride = levels.stride
    photos, targets = list(noisy.values()), list(renders.values())
    if stride > 1:
        photos, targets = shuffled(photos, stride), shuffled(targets, stride)
    # Trust target (the render only where it agrees with the photo within the noise) and the
    # blind-spot-loss guard: see denoise.round2.refine_round2.
    # Fine-tuning and inference with one torch thread per task, as in `denoise`: the result would depend on it.
    with one_thread_per_task():
        model, r2 = refine_round2(model, photos, targets, s.round2, seed=ctx.seed)
        # Keep the observation blend (denoise.fusion) for the fine-tuned model too: most of round 1's
        # quality comes from it, and without it round 2 fell from 23.97 to 20.92 dB on the demo scene
        # (8 views, 192x144, sigma 25/255).
        if r2.reverted and "previous" in ctx.inputs:
            # The guard kept the previous network: keep the previous round's images too (identical
            # up to the random maskings of inference), so a reverted round changes nothing.
            out = list(read_views(ctx.inputs["previous"], names).values())
        else:
            out = denoise_images(model, photos, passes=s.passes, seed=ctx.seed, fuse=True,
                                 noise_model=s.noise_model or levels.noise_model)
            if stride > 1:
                out = unshuffled(out, stride, [im.shape for im in noisy.values()])
    write_views(ctx.work_dir / "denoised", dict(zip(names, out, strict=True)))
    save_checkpoint(ctx.work_dir / MODEL_FILE, model)
    return RefineSummary(views=list(names), train=history_ends(model.history), pd_stride=stride,
                         round2=r2.to_json()).to_json()


#: The code each product stage runs besides its function's own module (`eval/pipeline/stages.py`,
#: `align_stage.py`, `fuse_stage.py`): all of `eval.pipeline` (views' PNG writing, calibration, stage
#: settings, splat training) and the component packages it calls, each with the project packages those
#: import (`splat` imports `denoise.losses`; `denoise` and `splat` import `mvgeo`).
#: Their source digests enter the stage keys (`eval.pipeline.stage`'s rule), so a changed constant or
#: function in any of them re-runs the stage and the stages after it.
STAGE_CODE: dict[str, tuple[str, ...]] = {
    "denoise": ("eval.pipeline", "denoise", "mvgeo"),
    "align": ("eval.pipeline", "mvgeo"),
    "fuse": ("eval.pipeline", "splat", "denoise", "mvgeo"),
    "splat": ("eval.pipeline", "splat", "denoise", "mvgeo"),
    "render": ("eval.pipeline", "splat", "denoise", "mvgeo"),
    "select": ("eval.pipeline", "denoise", "mvgeo"),
    "refine": ("eval.pipeline", "denoise", "mvgeo"),
}


def product_stages() -> PipelineStages:
    """The real Denoise-GS stages."""
    from eval.pipeline.publish import EXPORT_CODE, export

    return PipelineStages(denoise=denoise, align=align, splat=splat, render=render, select=select, refine=refine,
                          fuse=fuse, export=export, code={**STAGE_CODE, "export": EXPORT_CODE})
