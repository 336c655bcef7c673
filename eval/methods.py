"""The methods `denoise-gs eval` compares: one registry (`METHODS`) of what each one is, how it sets up
the pipeline, which stages it runs, and the folder it runs in.

- baselines (a)-(c): `3dgs_gt_poses` (the pipeline's splat stage on the noisy training photos with
  the ground-truth cameras), `instantsplat` (alignment + splat on the noisy photos),
  `nlm_instantsplat` (non-local means first);
- Denoise-GS (d), (e): `n2v_round1`, `denoise_gs`; the Table 3 round counts `rounds_1` ..
  `rounds_4`; the Table 2 ablations `ablate_no_selection`, `ablate_charbonnier`;
- the extension `n2v_fused_round1`, `denoise_gs_fused` (`PipelineConfig.fuse_noisy_splat`);
- `product`: the preset exactly as `denoise-gs run` ships it (its denoiser, rounds and fusion);
- the reference `oracle_clean`: the *clean* training photos through (b)'s alignment and the preset's splat,
  a perfect denoiser;
- `<method>@gt_poses` for every method with estimated poses: the photos its (last) splat trained on,
  splatted again with the ground-truth cameras (`gt_pose_variant`), so that the denoising's effect is
  seen apart from the method's pose error.

Methods that differ only in their number of rounds share a folder (`EvalMethod.family`), so they
reuse each other's completed rounds (the stage keys match); the ablations start from a link to
the Denoise-GS folder's round 1. Every value here is plain data or a module-level function, so a
method pickles (to run in another process).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import shutil
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from eval.baselines import (
    CLASSICAL_DENOISE_OUTPUTS,
    GtAlignSettings,
    gt_align,
    gt_align_inputs,
    identity_denoise,
    nlm_denoise,
    oracle_clean_denoise,
)
from eval.pipeline import PipelineConfig, PipelineStages, StageRunner, StageSpec, product_stages, run_pipeline
from eval.pipeline.config import DenoiseMethod
from eval.pipeline.inputs import WORKING_DIR
from eval.pipeline.run import RUN_COMMAND
from eval.pipeline.stage import completed_seconds
from eval.pipeline.stage_settings import splat_stage_settings, stage_seed
from eval.pipeline.stages import STAGE_CODE
from eval.pipeline.validate import DatasetFolder
from mvgeo.common.errors import DegenerateGeometryError, DisconnectedViewsError
from mvgeo.common.output import OwnerFile, read_manifest, remove_stale_leftovers, remove_tree, write_manifest

__all__ = ["GT_POSES_SUFFIX", "METHODS", "ORACLE_CLEAN", "EvalMethod", "Reconstruction", "gt_pose_variant",
           "reconstruct", "share_round1", "splat_photos", "with_splat_iters"]

_log = logging.getLogger(__name__)


# ----------------------------------------------------------------- how each method sets up the pipeline
def paper_loop(base: PipelineConfig) -> PipelineConfig:
    """The paper's loop, whatever the preset says: N2V (the methods that take `--denoiser` replace it), no
    noisy-photo fusion, splats trained on the round's photos as they are (no noisy-photo band,
    `SplatSettings.noisy_detail`) for InstantSplat's 1000 iterations (the `splat.train` preset's own
    length, whatever the preset's product splat runs), the denoised photos aligned, each round's own
    alignment, every round run. The baselines run it too: their splats see their own photos only, in their
    own recipe (the noisy photos' splat loses 0.7 dB from a second thousand iterations on DTU scan24,
    docs/bench/splat_length_real.md: a longer one would flatter the product). It denoises photos that read
    as clean too (`DenoiseSettings.pass_clean_below_255` 0)."""
    return dataclasses.replace(base, fuse_noisy_splat=False, stop_when_unrefined=False,
                               splat=dataclasses.replace(base.splat, noisy_detail=0.0, iters=None),
                               denoise=dataclasses.replace(base.denoise, method="n2v", pass_clean_below_255=0.0),
                               align=dataclasses.replace(base.align, reuse_geometry="never", photos="denoised"))


def clean_oracle(base: PipelineConfig) -> PipelineConfig:
    """`oracle_clean`: the paper's loop with the preset's splat length: the clean photos splatted as the
    product splats its denoised ones, so that the product's gap to it is its denoising's."""
    cfg = paper_loop(base)
    return dataclasses.replace(cfg, splat=dataclasses.replace(cfg.splat, iters=base.splat.iters))


def fused_loop(base: PipelineConfig) -> PipelineConfig:
    """The extension: each splat trains on the fused photos (and nothing more: no noisy-photo band), a round
    2 whose own alignment pins the views less well keeps round 1's geometry (`AlignSettings.reuse_geometry`);
    whether a round whose refine kept the previous network ends the loop is the preset's
    (`PipelineConfig.stop_when_unrefined`)."""
    return dataclasses.replace(base, fuse_noisy_splat=True, splat=dataclasses.replace(base.splat, noisy_detail=0.0),
                               align=dataclasses.replace(base.align, reuse_geometry="auto"))


def as_shipped(base: PipelineConfig) -> PipelineConfig:
    """The preset as it is: its denoiser, rounds, fusion and geometry reuse (`denoise-gs run`'s settings)."""
    return base


def no_selection(base: PipelineConfig) -> PipelineConfig:
    """Table 2 ablation: round 2 on every view."""
    return dataclasses.replace(paper_loop(base), select_views=False)


def charbonnier_round2(base: PipelineConfig) -> PipelineConfig:
    """Table 2 ablation: round 2's joint loss replaced by Charbonnier alone."""
    cfg = paper_loop(base)
    return dataclasses.replace(cfg, denoise=dataclasses.replace(cfg.denoise, round2_loss="charbonnier"))


def gt_poses_splat(base: PipelineConfig) -> PipelineConfig:
    """(a): the splat preset for known poses (`splat.train.TRAIN_PRESETS["gt_poses"]`: no pose learning)."""
    cfg = paper_loop(base)
    return dataclasses.replace(cfg, splat=dataclasses.replace(cfg.splat, preset="gt_poses"))


# ----------------------------------------------------------------- which stages each method runs
def product_eval_stages(dataset: DatasetFolder) -> PipelineStages:
    """The product's stages without the viewer export (the scores need no viewer files)."""
    return dataclasses.replace(product_stages(), export=None)


def identity_stages(dataset: DatasetFolder) -> PipelineStages:
    """(b): no denoiser."""
    return dataclasses.replace(product_eval_stages(dataset), denoise=identity_denoise,
                               denoise_outputs=CLASSICAL_DENOISE_OUTPUTS)


def nlm_stages(dataset: DatasetFolder) -> PipelineStages:
    """(c): non-local means as round 1's denoiser."""
    return dataclasses.replace(product_eval_stages(dataset), denoise=nlm_denoise,
                               denoise_outputs=CLASSICAL_DENOISE_OUTPUTS)


def oracle_clean_stages(dataset: DatasetFolder) -> PipelineStages:
    """`oracle_clean`: the clean training photos as round 1's "denoised" photos (the folder of the dataset's
    clean photos is an input of the denoise stage, so a changed clean photo re-runs it)."""
    folders = sorted({Path(p).parent for p in dataset.clean.values()})
    if len(folders) != 1:
        raise ValueError(f"oracle_clean reads the clean photos from one folder; the dataset's are in {folders}")
    return dataclasses.replace(product_eval_stages(dataset), denoise=oracle_clean_denoise,
                               denoise_outputs=CLASSICAL_DENOISE_OUTPUTS, denoise_inputs={"clean": folders[0]})


@dataclass(frozen=True)
class EvalMethod:
    """One method of `denoise-gs eval`.

    Attributes:
        name: its name on the command line (`--methods`) and in the results.
        family: the folder it runs in under `runs/<scene>/seed<k>/`, shared by methods that differ
            only in `rounds` (they reuse each other's completed rounds).
        description: what it is, in a few words.
        rounds: the pipeline's number of rounds; None keeps the preset's (`product`).
        configure: the pipeline settings from the evaluation's base settings (`rounds` is set after).
        stages: the stage functions, given the dataset (`oracle_clean` reads its clean photos).
        takes_denoiser: round 1 trains the UNet, with `EvalConfig.denoiser`'s objective: other than
            "n2v", the method's folder and row are named after it (`n2v_r2r`, `n2v_round1+r2r`).
        ground_truth_poses: no alignment: the splat stage trains with the dataset's cameras, and the
            held-out views are rendered at their true poses.
        shares_round1_with: the family whose completed round 1 is linked in before the run.
        gt_pose_variant_of: for `<method>@gt_poses` (`gt_pose_variant`), the method whose run it
            splats again with the ground-truth cameras (run, or resumed, first).
        gt_pose_points_from: for `<method>@gt_poses`, the method whose alignment points initialise the
            splat (the same for every variant: `oracle_clean`, the clean photos' alignment).
    """

    name: str
    family: str
    description: str
    rounds: int | None
    configure: Callable[[PipelineConfig], PipelineConfig]
    stages: Callable[[DatasetFolder], PipelineStages] = product_eval_stages
    takes_denoiser: bool = False
    ground_truth_poses: bool = False
    shares_round1_with: str | None = None
    gt_pose_variant_of: EvalMethod | None = None
    gt_pose_points_from: EvalMethod | None = None

    def _renamed(self, denoiser: DenoiseMethod) -> bool:
        return self.takes_denoiser and denoiser != "n2v"

    def pipeline_config(self, base: PipelineConfig, denoiser: DenoiseMethod = "n2v") -> PipelineConfig:
        """The pipeline settings this method runs with, from the evaluation's `base`."""
        cfg = self.configure(base)
        # Rounds and objective in one replace: the preset's objective may run one round only.
        change = {} if self.rounds is None else {"rounds": self.rounds}
        if self.takes_denoiser:
            change["denoise"] = dataclasses.replace(cfg.denoise, method=denoiser)
        return dataclasses.replace(cfg, **change)

    def folder(self, denoiser: DenoiseMethod = "n2v") -> str:
        """Its folder under `runs/<scene>/seed<k>/`."""
        if self.gt_pose_variant_of is not None:
            return self.gt_pose_variant_of.folder(denoiser) + GT_POSES_SUFFIX
        return f"{self.family}_{denoiser}" if self._renamed(denoiser) else self.family

    def runs_after(self, denoiser: DenoiseMethod = "n2v") -> tuple[str, ...]:
        """The folders whose runs must be complete before this one starts (its own when none): the
        ablations' linked round 1, a ground-truth-pose variant's method and its points' method."""
        if self.gt_pose_variant_of is not None:
            own = self.gt_pose_variant_of.runs_after(denoiser)
            points = self.gt_pose_points_from.runs_after(denoiser) if self.gt_pose_points_from else ()
            return tuple(dict.fromkeys(own + points))
        return (self.shares_round1_with or self.folder(denoiser),)

    def row_label(self, denoiser: DenoiseMethod = "n2v") -> str:
        """Its name in the results: with the denoiser appended when it is not N2V (`n2v_round1+r2r`,
        `n2v_round1+r2r@gt_poses`)."""
        if self.gt_pose_variant_of is not None:
            return self.gt_pose_variant_of.row_label(denoiser) + GT_POSES_SUFFIX
        return f"{self.name}+{denoiser}" if self._renamed(denoiser) else self.name


#: The name suffix of a ground-truth-pose variant (`gt_pose_variant`).
GT_POSES_SUFFIX = "@gt_poses"


@dataclass(frozen=True)
class _WithGtPosesSplat:
    """A method's settings with the known-pose splat preset (a value: equal after pickling)."""

    configure: Callable[[PipelineConfig], PipelineConfig]

    def __call__(self, base: PipelineConfig) -> PipelineConfig:
        cfg = self.configure(base)
        return dataclasses.replace(cfg, splat=dataclasses.replace(cfg.splat, preset="gt_poses"))


@dataclass(frozen=True)
class _WithSplatIters:
    """A method's settings with its splat trained for `iters` iterations (a value: equal after pickling)."""

    configure: Callable[[PipelineConfig], PipelineConfig]
    iters: int

    def __call__(self, base: PipelineConfig) -> PipelineConfig:
        cfg = self.configure(base)
        return dataclasses.replace(cfg, splat=dataclasses.replace(cfg.splat, iters=self.iters))


def with_splat_iters(method: EvalMethod, iters: int) -> EvalMethod:
    """`method` with every splat it runs (a ground-truth-pose variant's method and points included) trained
    for `iters` iterations, the baselines' too (`denoise-gs eval --splat-iters`)."""
    of, points = method.gt_pose_variant_of, method.gt_pose_points_from
    return dataclasses.replace(method, configure=_WithSplatIters(method.configure, iters),
                               gt_pose_variant_of=None if of is None else with_splat_iters(of, iters),
                               gt_pose_points_from=None if points is None else with_splat_iters(points, iters))


def gt_pose_variant(method: EvalMethod, points_from: EvalMethod) -> EvalMethod:
    """`<method>@gt_poses`: the photos `method`'s last splat trained on (its denoised photos, or the fused
    ones), splatted with the ground-truth cameras and no pose learning, initialised from `points_from`'s
    alignment points placed on the true cameras' rays (`eval.baselines.gt_align`). Every variant takes
    the same points (`ORACLE_CLEAN`'s: the clean photos' alignment, oracle information like the true
    cameras), so the variants differ only in their photos and their own method's splat recipe (its length
    and `noisy_detail`: under `default`, `product` and `oracle_clean` splat 2000 iterations, the noisy-photo
    baselines and `n2v_round1` 1000, the length each scores best at): against `oracle_clean@gt_poses` a
    variant shows what its denoising costs with the geometry taken out. (Each method's own points made the comparison
    one of starts: with the poses held, a splat cannot move a misplaced start in its iterations; on DTU
    scan24 the N2V photos scored 20.84 dB from N2V's own alignment points and 22.79 dB from the noisy
    photos'. The noisy photos' points fail where the noisy photos do not align, e.g. DTU at sigma 50.)"""
    if method.ground_truth_poses or method.gt_pose_variant_of is not None:
        raise ValueError(f"{method.name} has ground-truth poses already")
    return dataclasses.replace(
        method, name=method.name + GT_POSES_SUFFIX,
        description=f"{method.description}; its photos splatted with the ground-truth cameras",
        configure=_WithGtPosesSplat(method.configure), ground_truth_poses=True,
        shares_round1_with=None, gt_pose_variant_of=method, gt_pose_points_from=points_from)


#: The reference on the clean photos, also the source of every ground-truth-pose variant's initial points
#: (`gt_pose_variant`).
ORACLE_CLEAN = EvalMethod("oracle_clean", "oracle_clean", "reference: the clean photos through (b)'s alignment and "
                          "the preset's splat", 1, clean_oracle, oracle_clean_stages)


def _registry(*methods: EvalMethod) -> dict[str, EvalMethod]:
    return {m.name: m for m in methods}


#: Every method, in the order the evaluation runs them (the ablations after the round 1 they share).
_METHODS: dict[str, EvalMethod] = _registry(
    EvalMethod("3dgs_gt_poses", "3dgs_gt_poses", "(a) 3DGS on the noisy photos with ground-truth poses", 1,
               gt_poses_splat, ground_truth_poses=True),
    EvalMethod("instantsplat", "instantsplat", "(b) our alignment + splat on the noisy photos", 1, paper_loop,
               identity_stages),
    EvalMethod("nlm_instantsplat", "nlm_instantsplat", "(c) non-local means, then (b)", 1, paper_loop, nlm_stages),
    EvalMethod("n2v_round1", "n2v", "(d) Denoise-GS round 1 only", 1, paper_loop, takes_denoiser=True),
    EvalMethod("denoise_gs", "n2v", "(e) Denoise-GS, 2 rounds", 2, paper_loop, takes_denoiser=True),
    EvalMethod("ablate_no_selection", "ablate_no_selection", "Table 2: round 2 on every view", 2, no_selection,
               shares_round1_with="n2v"),
    EvalMethod("ablate_charbonnier", "ablate_charbonnier", "Table 2: Charbonnier loss in round 2", 2,
               charbonnier_round2, shares_round1_with="n2v"),
    *(EvalMethod(f"rounds_{n}", "n2v", f"Table 3: Denoise-GS with {n} round(s)", n, paper_loop, takes_denoiser=True)
      for n in (1, 2, 3, 4)),
    EvalMethod("n2v_fused_round1", "n2v_fused", "extension: (d) with the noisy-photo fusion", 1, fused_loop,
               takes_denoiser=True),
    EvalMethod("denoise_gs_fused", "n2v_fused", "extension: (e) with the noisy-photo fusion", 2, fused_loop,
               takes_denoiser=True),
    EvalMethod("product", "product", "the product: `denoise-gs run` with the preset as shipped", None, as_shipped),
    ORACLE_CLEAN,
)
#: ... then each one's ground-truth-pose variant (`gt_pose_variant`).
METHODS: dict[str, EvalMethod] = {**_METHODS, **_registry(*(gt_pose_variant(m, ORACLE_CLEAN)
                                                            for m in _METHODS.values() if not m.ground_truth_poses))}


# ----------------------------------------------------------------- running one
@dataclass(frozen=True)
class Reconstruction:
    """What a method produced, for scoring.

    Attributes:
        round_dir: the folder holding `point_cloud.ply` and `sparse/0/` (the last round's).
        estimated_poses: True when the poses were estimated (they are registered to the ground
            truth for scoring); False when they are the ground truth.
        seconds: the stages' own recorded wall seconds (a stage reused from the cache counts the
            time it took when it ran).
    """

    round_dir: Path
    estimated_poses: bool
    seconds: float


def share_round1(src_run: Path, dst_run: Path) -> bool:
    """Seed `dst_run/round1` with hard links to a completed `src_run/round1` (same round-1 settings).

    The Table 2 ablations differ from `denoise_gs` only from round 2 on; linking round 1 lets
    their stage keys match it and skip it (the stage runner still checks every key, so a
    mismatch just re-runs). Returns True when something was linked.
    """
    src, dst = Path(src_run) / "round1", Path(dst_run) / "round1"
    if dst.exists() or not (src / "stages").is_dir():
        return False
    dst.parent.mkdir(parents=True, exist_ok=True)
    # A temporary folder with an owner file (`mvgeo.common.output.OwnerFile`), as the commands' own: one that a
    # killed call left (a worker killed while linking) is taken for a leftover and removed, by the next call
    # here and by `prepare_output` when the evaluation opens this run folder again, instead of making the
    # run folder one that holds files `denoise-gs run` did not write (a resumed evaluation was refused).
    remove_stale_leftovers(dst.parent, dst.name)
    tmp = dst.parent / f".{dst.name}.tmp-{uuid.uuid4().hex[:8]}"
    owner = OwnerFile(tmp)

    def link(a: str, b: str) -> None:
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    try:
        shutil.copytree(src, tmp, copy_function=link,
                        ignore=lambda d, names: [n for n in names if n.startswith(".")])
        os.replace(tmp, dst)
    finally:
        if os.path.lexists(tmp):
            remove_tree(tmp)
        owner.release()
    if read_manifest(dst_run) is None:  # the run folder is ours: `denoise-gs run` resumes into it
        write_manifest(dst_run, RUN_COMMAND, record_files=False)
    return True


def splat_photos(round_dir: Path, fused: bool) -> Path:
    """The photos a pipeline round's splat trained on: `fused/` when its run fused (`fused`:
    `PipelineConfig.fuse_noisy_splat`), else `denoised/`. Decided by the settings, not by what the folder
    holds: a `fused/` an earlier run left there (with fusion on) is not what this run's splat trained on."""
    return Path(round_dir) / ("fused" if fused else "denoised")


#: The code the ground-truth-pose align stage (`eval.baselines.gt_align`) runs besides its own module (the
#: rule: `eval.pipeline.stage`): the splat's packages (`splat.dataset.points_from_depth`) and `eval.heldout`
#: (`register_sim3` places a variant's points on the true cameras' rays), so that an edit in either re-runs it.
GT_ALIGN_CODE: tuple[str, ...] = (*STAGE_CODE["splat"], "eval.heldout")


def _splat_on_ground_truth(stages: PipelineStages, config: PipelineConfig, dataset: DatasetFolder, inputs: Path,
                           folder: Path, estimate: Path | None = None, noisy: Path | None = None) -> Reconstruction:
    """(a) and the `@gt_poses` variants: `gt_align` then the pipeline's splat stage on the photos in
    `inputs`, in `folder/round1` (resumable like the pipeline's rounds). `estimate`: a pipeline round
    folder whose alignment points initialise the splat (a variant's points' method; `gt_align`).
    `noisy`: the noisy working photos of `inputs`' views, whose finest band the splat's target takes back
    under `config.splat.noisy_detail` (default `inputs` itself, which adds nothing)."""
    rd = folder / "round1"
    runner = StageRunner()
    align_inputs = gt_align_inputs(dataset, estimate)
    al = runner.run(StageSpec("align", rd, functools.partial(gt_align, dataset), ("align",), inputs=align_inputs,
                              hashed_inputs=tuple(align_inputs), settings=GtAlignSettings(tuple(dataset.train)),
                              code=GT_ALIGN_CODE), label="gt_poses/align")
    seed = stage_seed(config.seed, 1, "splat")
    settings = splat_stage_settings(config, seed=seed)
    splat_inputs, hashed = {"images": inputs, "align": rd / "align"}, ("images",)
    if settings.noisy_detail.weight > 0:
        splat_inputs["noisy"], hashed = (inputs if noisy is None else noisy), ("images", "noisy")
    sp = runner.run(StageSpec("splat", rd, stages.splat, ("sparse", "point_cloud.ply"),
                              inputs=splat_inputs, hashed_inputs=hashed, upstream=(al,), settings=settings,
                              seed=seed, code=stages.code.get("splat", ())), label="gt_poses/splat")
    return Reconstruction(rd, False, float(al.seconds + sp.seconds))


def _denoised_before_refusal(method: EvalMethod, config: PipelineConfig, folder: Path,
                             err: DegenerateGeometryError | DisconnectedViewsError) -> Reconstruction:
    """A `@gt_poses` variant's photos when its method's own alignment refused them: round 1's completed
    `denoised/` (what its splat would have trained on). The variant needs the photos, not the method's
    poses, so a scene whose photos the method cannot align (the temple ring at sigma 25) still shows
    what its denoising does with the true cameras. Re-raises `err` where round 1 did not get that far, where
    the splat would have trained on fused photos (they need the noisy photos' splat), or where a method of
    several rounds has round 1's splat recorded (a later round refused; its photos are not round 1's). A
    method of one round refused in round 1 whatever records an earlier run with other settings left there."""
    rd = folder / "round1"
    if config.fuse_noisy_splat or (config.rounds > 1 and (rd / "stages" / "splat.json").is_file()):
        raise err
    seconds = completed_seconds(rd, "denoise")  # None: no record, or a commit that was cut short
    if seconds is None:
        raise err
    _log.warning("%s: its alignment refused the photos (%s); the ground-truth-pose variant splats round 1's "
                 "denoised photos", method.name, str(err).split(":")[0])
    return Reconstruction(rd, True, seconds)


def reconstruct(method: EvalMethod, dataset: DatasetFolder, base: PipelineConfig, *, seed: int,
                denoiser: DenoiseMethod, inputs: Path, seed_dir: Path, wait_for_lock: bool = False) -> Reconstruction:
    """Run (or resume) `method` with `seed` on the noisy training photos in `inputs`, in
    `seed_dir/<its folder>`. A `@gt_poses` variant runs (or resumes) its method and its points' method
    first; its seconds are the method's plus its own splat's.

    `wait_for_lock`: where another process holds the run folder, wait for it instead of raising
    (`run_pipeline`). A variant sets it for its method's and its points' method's runs, which other
    variants of the evaluation may be reading at the same time (`eval.evaluate.task_graph`).

    Raises:
        Whatever the stages raise (`InputError`, `DegenerateGeometryError` for inputs the method
        cannot handle).
    """
    config = method.pipeline_config(dataclasses.replace(base, seed=seed), denoiser)
    stages = method.stages(dataset)
    folder = seed_dir / method.folder(denoiser)
    if method.gt_pose_variant_of is not None:
        try:
            own = reconstruct(method.gt_pose_variant_of, dataset, base, seed=seed, denoiser=denoiser, inputs=inputs,
                              seed_dir=seed_dir, wait_for_lock=True)
        except (DegenerateGeometryError, DisconnectedViewsError) as err:
            own_method = method.gt_pose_variant_of
            own = _denoised_before_refusal(own_method, config, seed_dir / own_method.folder(denoiser), err)
        points = own if method.gt_pose_points_from in (None, method.gt_pose_variant_of) else reconstruct(
            method.gt_pose_points_from, dataset, base, seed=seed, denoiser=denoiser, inputs=inputs, seed_dir=seed_dir,
            wait_for_lock=True)
        photos = splat_photos(own.round_dir, config.fuse_noisy_splat)  # the variant's fusion is its method's
        rec = _splat_on_ground_truth(stages, config, dataset, photos, folder, estimate=points.round_dir,
                                     noisy=own.round_dir.parent / WORKING_DIR)
        return dataclasses.replace(rec, seconds=own.seconds + rec.seconds)
    if method.ground_truth_poses:
        return _splat_on_ground_truth(stages, config, dataset, inputs, folder)
    if method.shares_round1_with is not None:
        share_round1(seed_dir / method.shares_round1_with, folder)
    res = run_pipeline(inputs, folder, config, stages=stages, wait_for_lock=wait_for_lock)
    ran = [*res.rounds, *([res.stopped] if res.stopped is not None else [])]  # a stopped round's stages cost too
    seconds = float(sum(st.seconds for rd in ran for st in rd.stages.values()))
    return Reconstruction(res.rounds[-1].dir, True, seconds)
