"""`run_pipeline`: Denoise-GS's rounds as resumable stages.

Round 1: denoise (train N2V on every noisy image, denoise all) -> align ->
splat (training with pose optimisation) -> render at every input pose. With
`fuse_noisy_splat` (an extension), a fuse stage between align and splat
averages each denoised photo with a render of a splat of the noisy photos, and
the splat trains on those; in rounds >= 2 it reuses the previous round's renders
of that splat when the round's alignment and noisy photos are the previous
round's (`reuse_noisy_splat`).
Round r >= 2: select views from round r-1 (pose k-means, K = `views`, sharpest
per cluster) -> refine (fine-tune the round r-1 UNet with the joint loss
against round r-1's renders of the selected views, denoise them) -> align
(keeping the better-determined of its own and round r-1's focal length, and
round r-1's poses when they determine the selected views better,
`eval.pipeline.calibration`) -> splat -> render.

Before round 1 the inputs are made upright (EXIF) and downscaled once to the
working size (`PipelineConfig.max_size`, `eval.pipeline.inputs`); after the last
round the export stage writes the scene for viewers (`eval.pipeline.publish`).

Layout (each stage commits its outputs atomically; `roundN/stages/*.json`
(and `OUT/stages/*.json` for inputs and export) hold the keys and each output
file's size and sha256, checked before a resumed run reuses them; see
`eval.pipeline.stage`):

    OUT/inputs/*.png, inputs/sizes.json            (inputs: the working images, input and working sizes)
    OUT/roundN/denoised/*.png, n2v_model.pt      (denoise / refine)
    OUT/roundN/align/sparse/0/, points.npz        (align: initial poses and points)
    OUT/roundN/fused/, noisy_renders/             (fuse, with fuse_noisy_splat)
    OUT/roundN/sparse/0/, point_cloud.ply         (splat: optimised poses, Gaussians)
    OUT/roundN/renders/*.png                      (render)
    OUT/roundN/selection.json                     (select, rounds >= 2)
    OUT/scene.splat, OUT/view/index.html           (export: .splat and offline viewer of the last round)
    OUT/cameras/working/, OUT/cameras/input/      (export: final cameras at working and input size)
    OUT/report.json, OUT/report.md, OUT/report_files/*.png   (recorded in OUT/stages/report.json)

A resumed run changes only files it wrote: before any stage runs, the outputs of every stage it may run
(and the published files: export's and the report's) are checked against their records, and a file the
run did not write, or one whose content changed, stops it (`UnownedOutputError`, exit code 2) with nothing
changed (`run_pipeline`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator
from dataclasses import dataclass, fields
from pathlib import Path

from eval.pipeline.config import PipelineConfig
from eval.pipeline.hashing import hash_files
from eval.pipeline.inputs import SIZES_FILE, WORKING_DIR, prepare_inputs
from eval.pipeline.lock import output_lock
from eval.pipeline.publish import EXPORT_OUTPUTS
from eval.pipeline.report import REPORT_OUTPUTS, REPORT_RECORD, write_report
from eval.pipeline.rounds import RoundResult, StoppedRound
from eval.pipeline.stage import (
    OwnershipCheck,
    StageResult,
    StageRunner,
    StageSpec,
    check_outputs_owned,
    code_digests,
    withdraw_outputs,
)
from eval.pipeline.stage_settings import (
    InputsStageSettings,
    RefineStageSettings,
    RoundSettings,
    round_settings,
    stage_seed,
)
from eval.pipeline.stages import MODEL_FILE, PASS_THROUGH_UNWRITTEN, PipelineStages, product_stages
from eval.pipeline.summaries import DenoiseSummary, RefineSummary
from eval.pipeline.validate import validate_run_inputs
from mvgeo.common.output import prepare_output, resumable_output_dir
from mvgeo.common.timing import StageTimer

__all__ = ["PipelineResult", "RoundResult", "run_pipeline", "stage_seed"]

_log = logging.getLogger(__name__)


#: The command named in a run folder's manifest (`mvgeo.common.output`).
RUN_COMMAND = "denoise-gs run"
#: The outputs of each stage of a round, relative to the round's folder.
SCENE_OUTPUTS = {"align": ("align",), "fuse": ("fused", "noisy_renders"), "splat": ("sparse", "point_cloud.ply"),
                 "render": ("renders",)}
ROUND2_OUTPUTS = {"select": ("selection.json",), "refine": ("denoised", MODEL_FILE)}


@dataclass(frozen=True)
class PipelineResult:
    """What `run_pipeline` produced.

    Attributes:
        out: the output folder.
        rounds: per-round stage results of the rounds that ran to the end; the last one's
            reconstruction is the result.
        timings_s: this invocation's seconds per stage (`roundN/stage`) and `total`;
            skipped stages are absent.
        report_json, report_md: the report files.
        stopped: the round the loop stopped in (`PipelineConfig.stop_when_unrefined`), if any.
    """

    out: Path
    rounds: list[RoundResult]
    timings_s: dict[str, float]
    report_json: Path
    report_md: Path
    stopped: StoppedRound | None = None


def _hash_stage_code(stages: PipelineStages) -> None:
    """Take the source digests of every stage's code now, before any stage runs: they are cached for
    the process (`eval.pipeline.hashing.source_digest`), so an edit made while the run is in progress
    is not recorded against results of the code loaded before it."""
    for f in fields(stages):
        fn = getattr(stages, f.name)
        if callable(fn):
            code_digests(fn, stages.code.get(f.name, ()))


def _scene_stages(runner: StageRunner, stages: PipelineStages, rd: Path, images: StageResult,
                  config: PipelineConfig, settings: RoundSettings, *, working: Path,
                  previous: RoundResult | None = None) -> dict[str, StageResult]:
    """align -> [fuse ->] splat -> render on the round's denoised images (`previous`: round r-1, for
    r >= 2; `working`: the working images, which the fuse stage reads)."""
    r = settings.index
    label = f"round{r}"
    # `working`: the prepare stage's sizes.json carries the input photos' EXIF focal (the align stage's prior).
    inputs, upstream = {"images": rd / "denoised", "working": working}, (images,)
    if settings.align.reads_noisy:  # round 1: the noisy working photos are aligned too (AlignSettings.photos)
        inputs["noisy"] = working
    if previous is not None:  # the previous round's calibration (eval.pipeline.calibration)
        inputs["previous_align"] = previous.dir / "align"
        upstream = (images, previous.stages["align"])
    hashed: tuple[str, ...] = ()
    if config.align.intrinsics is not None:  # the user's calibration: its content enters the key
        inputs["intrinsics"], hashed = Path(config.align.intrinsics), ("intrinsics",)
    al = runner.run(StageSpec("align", rd, stages.align, SCENE_OUTPUTS["align"], inputs=inputs, upstream=upstream,
                              hashed_inputs=hashed, settings=settings.align, seed=stage_seed(config.seed, r, "align"),
                              code=stages.code.get("align", ())),
                    label=f"{label}/align")
    out: dict[str, StageResult] = {"align": al}
    splat_images, splat_upstream = rd / "denoised", (images, al)
    if settings.fuse is not None:
        if stages.fuse is None:
            raise ValueError("fuse_noisy_splat is on but the stages have no fuse function")
        fuse_inputs = {"noisy": working, "images": rd / "denoised", "align": rd / "align"}
        fuse_upstream: tuple[StageResult, ...] = (images, al)
        if settings.fuse.reuse_noisy_splat and previous is not None and "fuse" in previous.stages:
            # What the previous round's noisy-photo splat was trained from and rendered
            # (`eval.pipeline.fuse_stage.fuse` reuses its renders when this round's inputs are the same).
            fuse_inputs.update(previous_align=previous.dir / "align", previous_noisy=working,
                               previous_noisy_renders=previous.dir / "noisy_renders")
            fuse_upstream += (previous.stages["align"], previous.stages["fuse"])
        fu = runner.run(StageSpec("fuse", rd, stages.fuse, SCENE_OUTPUTS["fuse"], inputs=fuse_inputs,
                                  upstream=fuse_upstream, settings=settings.fuse,
                                  seed=stage_seed(config.seed, r, "fuse"), code=stages.code.get("fuse", ())),
                        label=f"{label}/fuse")
        out["fuse"] = fu
        splat_images, splat_upstream = rd / "fused", (images, al, fu)
    splat_inputs = {"images": splat_images, "align": rd / "align"}
    if settings.splat.noisy_detail.weight > 0:  # the target takes back the noisy photos' finest band
        splat_inputs["noisy"] = working
    sp = runner.run(StageSpec("splat", rd, stages.splat, SCENE_OUTPUTS["splat"],
                              inputs=splat_inputs, upstream=splat_upstream,
                              settings=settings.splat, seed=stage_seed(config.seed, r, "splat"),
                              code=stages.code.get("splat", ())),
                    label=f"{label}/splat")
    re = runner.run(StageSpec("render", rd, stages.render, SCENE_OUTPUTS["render"],
                              inputs={"sparse": rd / "sparse", "scene": rd / "point_cloud.ply"}, upstream=(sp,),
                              settings=settings.render, seed=0, code=stages.code.get("render", ())),
                    label=f"{label}/render")
    return {**out, "splat": sp, "render": re}


def refine_settings_as_round1(refine: RefineStageSettings, denoised: StageResult) -> RefineStageSettings:
    """`refine` with round 1's pixel-shuffle stride and noise model where it would measure its own (`pd_stride`
    0, no `noise_model`), read from round 1's denoise summary (`denoised`; unchanged where that does not
    record them).

    Every later round fine-tunes the network round 1 trained, which learned the photos at round 1's stride; the
    refine stage measured the stride again on its K selected views only, and a subset can read otherwise
    (noise levels that differ from photo to photo, near `denoise.pixel_shuffle.MIN_NOISE_STD`): the network
    would then be fine-tuned and applied at a stride it never learned."""
    summary = DenoiseSummary.from_json(denoised.summary)
    if summary.pd_stride is None:
        return refine
    changes: dict[str, object] = {}
    if refine.pd_stride == 0:
        changes["pd_stride"] = summary.pd_stride
    if refine.noise_model is None:  # round 1's: `NoiseLevels.noise_model` of its measurement
        changes["noise_model"] = "luma" if summary.noise_level_luma_255 is not None else "auto"
    return dataclasses.replace(refine, **changes)


def planned_run_outputs(out: Path, stages: PipelineStages,
                     settings: list[RoundSettings]) -> Iterator[tuple[Path, str, tuple[str, ...]]]:
    """(stage folder, stage name, outputs) of every stage a run of `settings` may run, then the published
    ones (export, if `stages` has it, and the report)."""
    yield out, WORKING_DIR, (WORKING_DIR,)
    for rs in settings:
        rd = out / f"round{rs.index}"
        first = {"denoise": stages.denoise_outputs} if rs.index == 1 else ROUND2_OUTPUTS
        scene = {k: v for k, v in SCENE_OUTPUTS.items() if k != "fuse" or rs.fuse is not None}
        for name, outputs in {**first, **scene}.items():
            yield rd, name, outputs
    yield from _published(out, stages)


def _check_run_outputs(out: Path, stages: PipelineStages, settings: list[RoundSettings]) -> None:
    """`check_outputs_owned` for every stage of `planned_run_outputs`; one error names every file found.

    Raises:
        UnownedOutputError: files the run did not write, or that changed, in the outputs of those stages.
    """
    owned = OwnershipCheck()
    for folder, name, outputs in planned_run_outputs(out, stages, settings):
        owned.check(check_outputs_owned, folder, name, outputs, defer_hidden=True)
    owned.raise_if_any(out)


def _published(out: Path, stages: PipelineStages) -> list[tuple[Path, str, tuple[str, ...]]]:
    """(folder, record name, outputs) of the run's published result: export's files and the report."""
    export = [(out, "export", EXPORT_OUTPUTS)] if stages.export is not None else []
    return [*export, (out, REPORT_RECORD, REPORT_OUTPUTS)]


def run_pipeline(images_dir: str | Path, out: str | Path, config: PipelineConfig, *,
                 stages: PipelineStages | None = None, force: bool = False,
                 wait_for_lock: bool = False) -> PipelineResult:
    """Run (or resume) Denoise-GS on a folder of noisy, unposed images.

    Args:
        images_dir: folder of noisy images (PNG/JPEG/TIFF/WebP, 8 or 16 bit).
        out: output folder (created; one run at a time, enforced by a lock file). A new or empty
            folder, or a previous run's (resumed); anything else, or one that is, holds or lies
            inside `images_dir`, is refused before any work (`mvgeo.common.output`).
        config: settings (see `eval.pipeline.config.PRESETS`).
        stages: the stage functions; default the product's (`product_stages()`).
        force: re-run every stage even when complete outputs exist.
        wait_for_lock: where another process is running in `out`, wait for it to finish instead of raising
            (`eval.pipeline.lock.output_lock`). `denoise-gs eval`'s ground-truth-pose variants set it for the
            runs they start from, which several of them may read at once (`eval.evaluate.task_graph`).

    Resuming changes only files the run wrote. Before any stage runs, the committed outputs of every stage
    this run may run, and the published result (`scene.splat`, `view/`, `cameras/`, the report files), are
    checked against their records (size and sha256 of every file): a file the run did not write, or one
    whose content changed, stops the run with nothing changed; a recorded file that is missing is written
    again. Hidden files (e.g. `.DS_Store`) in complete outputs are checked only when their stage runs again:
    a resume that recomputes nothing keeps working beside them, and one that must recompute that stage stops
    there, the hidden file untouched (the stages before it, and the withdrawal of the published result, may
    have happened by then: both touch only the run's own files).
    When a stage is about to be recomputed, the previous published result is withdrawn first (its files
    and records removed, after the same check), so a run killed afterwards leaves no report, scene or
    cameras that do not match its stages; a run with nothing to recompute keeps them, and rewrites only
    the report (this invocation's timings).

    Raises:
        InputError: bad inputs or settings (e.g. a preset name a component does not have), found
            before any compute (see `validate_run_inputs`, `eval.pipeline.stage_settings`).
        UnownedOutputError: (an `InputError`) files in `out` that the run would have to replace or
            delete but did not write, or that changed since (named in the message; nothing changed).
        ValueError: `stages` cannot run `config` (no fuse function with `fuse_noisy_splat`, or a
            denoise stage without a network before a second round).
    """
    images_dir, out = Path(images_dir), Path(out)
    plan = prepare_output(out, command=RUN_COMMAND, inputs=[images_dir, config.align.intrinsics], resume=True)
    files = validate_run_inputs(images_dir, config)
    stages = product_stages() if stages is None else stages
    if config.rounds >= 2 and MODEL_FILE not in stages.denoise_outputs:
        raise ValueError(f"round 2 fine-tunes round 1's {MODEL_FILE}, which this denoise stage does not write "
                         f"(outputs {list(stages.denoise_outputs)}): run it with rounds=1")
    # Every stage's typed settings, resolved now: a preset a component lacks fails before any compute,
    # and a changed component default changes the keys of the stages that use it.
    settings = [round_settings(config, r) for r in range(1, config.rounds + 1)]
    timer = StageTimer()
    withdrawn = False

    def withdraw_published(spec: StageSpec) -> None:
        """Before the first stage that is recomputed: remove the previous published result (the run's own)."""
        nonlocal withdrawn
        if not withdrawn:
            withdrawn = True
            # The report first: a run killed in between leaves no report naming a scene that is gone.
            if any([withdraw_outputs(folder, name, outputs)
                    for folder, name, outputs in reversed(_published(out, stages))]):
                _log.info("stage %s runs again: the previous scene, cameras and report were withdrawn", spec.name)

    runner = StageRunner(timer=timer, force=force, before_change=withdraw_published)
    # The noisy inputs enter the keys by content (only the image files, so
    # unrelated files in IMAGES_DIR change nothing).
    noisy_digest = hash_files(files.values())
    _hash_stage_code(stages)
    rounds: list[RoundResult] = []
    stopped: StoppedRound | None = None
    with resumable_output_dir(plan), output_lock(out, wait=wait_for_lock):
        _check_run_outputs(out, stages, settings)  # before anything is changed
        # The working images (upright, long side <= max_size): every stage reads these, not the inputs.
        prep = runner.run(StageSpec(WORKING_DIR, out, prepare_inputs, (WORKING_DIR,), inputs={"noisy": images_dir},
                                    settings=InputsStageSettings(config.max_size, noisy_digest),
                                    code=("eval.pipeline", "mvgeo")), label=WORKING_DIR)
        working = out / WORKING_DIR
        rd = out / "round1"
        den = runner.run(StageSpec(
            "denoise", rd, stages.denoise, stages.denoise_outputs, inputs={**stages.denoise_inputs, "noisy": working},
            hashed_inputs=tuple(sorted(stages.denoise_inputs)), upstream=(prep,),
            settings=settings[0].denoise, seed=stage_seed(config.seed, 1, "denoise"),
            code=stages.code.get("denoise", ()),
            optional=tuple(o for o in stages.denoise_outputs if o in PASS_THROUGH_UNWRITTEN)),
            label="round1/denoise")
        scene = _scene_stages(runner, stages, rd, den, config, settings[0], working=working)
        rounds.append(RoundResult(1, rd, {"denoise": den, **scene}))
        for rs in settings[1:]:
            r = rs.index
            prev, rd = rounds[-1], out / f"round{r}"
            if r == 2 and MODEL_FILE not in den.outputs:  # round 1 passed its photos through: no network
                stopped = StoppedRound(r, rd, {}, f"round {r} not run: round 1's photos read as clean and were "
                                                  "not denoised, so there is no network to fine-tune; round 1's "
                                                  "reconstruction is the result")
                _log.info("%s", stopped.reason)
                break
            model_stage = prev.stages.get("denoise") or prev.stages["refine"]
            sel = runner.run(StageSpec(
                "select", rd, stages.select, ROUND2_OUTPUTS["select"],
                inputs={"sparse": prev.dir / "sparse", "images": prev.dir / "denoised"},
                upstream=(prev.stages["splat"], model_stage), settings=rs.select,
                seed=stage_seed(config.seed, r, "select"), code=stages.code.get("select", ())),
                label=f"round{r}/select")
            ref = runner.run(StageSpec(
                "refine", rd, stages.refine, ROUND2_OUTPUTS["refine"],
                inputs={"noisy": working, "selection": rd / "selection.json",
                        "model": prev.dir / MODEL_FILE, "renders": prev.dir / "renders",
                        "previous": prev.dir / "denoised"},
                upstream=(sel, model_stage, prev.stages["render"]), settings=refine_settings_as_round1(rs.refine, den),
                seed=stage_seed(config.seed, r, "refine"), code=stages.code.get("refine", ())),
                label=f"round{r}/refine")
            kept, why = RefineSummary.from_json(ref.summary).kept_previous()
            if kept and config.stop_when_unrefined:
                stopped = StoppedRound(r, rd, {"select": sel, "refine": ref},
                                       f"round {r} stopped after its refine: {why}; round {prev.index}'s "
                                       "reconstruction is the result")
                _log.info("%s", stopped.reason)
                break
            scene = _scene_stages(runner, stages, rd, ref, config, rs, working=working, previous=prev)
            rounds.append(RoundResult(r, rd, {"select": sel, "refine": ref, **scene}))
        exported = None
        if stages.export is not None:
            last = rounds[-1]
            exported = runner.run(StageSpec(
                "export", out, stages.export, EXPORT_OUTPUTS,
                inputs={"scene": last.dir / "point_cloud.ply", "sparse": last.dir / "sparse",
                        "sizes": working / SIZES_FILE},
                upstream=(prep, last.stages["splat"]), code=stages.code.get("export", ())), label="export")
        report_json, report_md = write_report(out, images_dir=images_dir, config=config, rounds=rounds,
                                              timings_s=timer.as_dict(), working=prep, exported=exported,
                                              stopped=stopped)
    _log.info("report: %s", report_md)
    return PipelineResult(out, rounds, timer.as_dict(), report_json, report_md, stopped)
