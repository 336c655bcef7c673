"""`denoise-gs run | eval | cost | dataset`: the product's command line (thin: parse, validate, call the library).

Every input problem is reported before any compute, with exit code 2.
"""

from __future__ import annotations

from mvgeo.common.threads import apply_thread_policy

# Before the imports below load torch: OpenMP reads OMP_WAIT_POLICY once, when it loads
# (mvgeo.common.threads.apply_thread_policy; docs/conventions.md, "Threads").
apply_thread_policy()

import argparse
import dataclasses
import importlib.util
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from denoise.inference import NOISE_MODELS
from denoise.pixel_shuffle import MAX_STRIDE
from eval.distributed import ClusterSettings, check_ray_address, ray_cluster
from eval.evaluate import EvalConfig, evaluate_dataset, scene_dataset
from eval.methods import GT_POSES_SUFFIX, METHODS
from eval.pipeline import PRESETS, preset, run_pipeline, validate_dataset_folder
from eval.pipeline.config import ALIGN_PHOTOS, DENOISE_METHODS, PASS_CLEAN_BELOW_255, PipelineConfig
from eval.pipeline.inputs import working_dataset
from eval.pipeline.lock import output_lock
from eval.pipeline.validate import MIN_IMAGE_SIZE_PX, check_renderable_cameras
from eval.real.cli import add_dataset_parser
from eval.results import carried_rows, merge_rows, write_results
from mvgeo.common.argtypes import (
    fraction,
    half_open_fraction,
    int_range,
    nonneg_float,
    nonneg_int,
    out_path,
    positive_int,
    seed,
)
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.device import DEVICE_HELP, resolve_device
from mvgeo.common.errors import AlignmentRefusedError, DisconnectedViewsError, InputError
from mvgeo.common.output import OUT_RESUME_HELP, prepare_output, resumable_output_dir

__all__ = ["build_parser", "main", "resolve_scene_source"]

_log = logging.getLogger(__name__)

def _builtin_scenes() -> list[str]:
    # Located without importing data_synth (its import pulls in open3d: seconds).
    spec = importlib.util.find_spec("data_synth")
    if spec is None or not spec.submodule_search_locations:
        return []
    names = set()
    for loc in spec.submodule_search_locations:
        names.update(p.stem for p in (Path(loc) / "scenes").glob("*.toml"))
    return sorted(names)


def resolve_scene_source(scene: str) -> tuple[str, Path | str]:
    """Classify `SCENE_OR_DATASET`: ("dataset", folder) | ("scene_file", path) | ("builtin", name).

    A dataset folder is fully validated (`validate_dataset_folder`); a scene
    file must exist; a built-in name must be one `data_synth` ships.

    Raises:
        InputError: none of the three, or an invalid dataset folder.
    """
    path = Path(scene)
    if path.is_dir():
        validate_dataset_folder(path)
        return "dataset", path
    if path.suffix == ".toml":
        if not path.is_file():
            raise InputError("scene file does not exist", path=path)
        return "scene_file", path
    names = _builtin_scenes()
    if scene in names:
        return "builtin", scene
    raise InputError(f"{scene!r} is neither a dataset folder, a scene .toml file, nor a built-in scene",
                     fix=f"built-in scenes: {', '.join(names) or '(data_synth not installed)'}")


def _cmd_run(args: argparse.Namespace) -> int:
    device = None if args.device is None else str(resolve_device(args.device))
    # The rounds go in last: whether a round 2 can run depends on the denoiser (`--denoiser`) set below.
    config = preset(args.preset, views=args.views, seed=args.seed,
                    select_views=False if args.no_select else None, device=device)
    if args.allow_focal_prior:
        config = _allow_focal_prior(config)
    if args.fuse_noisy_splat is not None:
        config = dataclasses.replace(config, fuse_noisy_splat=args.fuse_noisy_splat)
    if args.reuse_intrinsics is not None:
        config = dataclasses.replace(config, align=dataclasses.replace(config.align,
                                                                       reuse_intrinsics=args.reuse_intrinsics))
    if args.align_photos is not None:
        config = dataclasses.replace(config, align=dataclasses.replace(config.align, photos=args.align_photos))
    if args.intrinsics is not None:
        config = dataclasses.replace(config, align=dataclasses.replace(config.align, intrinsics=str(args.intrinsics)))
    config = dataclasses.replace(config, max_size=args.max_size)
    if args.denoiser is not None:
        config = dataclasses.replace(config, denoise=dataclasses.replace(config.denoise, method=args.denoiser))
    if args.keep_noisy is not None:
        config = dataclasses.replace(config, denoise=dataclasses.replace(config.denoise, keep_noisy=args.keep_noisy))
    if args.wiener is not None:
        config = dataclasses.replace(config, denoise=dataclasses.replace(config.denoise, wiener=args.wiener))
    if args.grouped_wiener is not None:
        config = dataclasses.replace(config, denoise=dataclasses.replace(config.denoise,
                                                                         grouped_wiener=args.grouped_wiener))
    if args.grouped_wiener_passes is not None:
        if args.grouped_wiener is False:
            raise InputError(f"--no-grouped-wiener turns the step off, --grouped-wiener-passes "
                             f"{args.grouped_wiener_passes} asks for passes of it",
                             fix="give one of the two options")
        config = dataclasses.replace(config, denoise=dataclasses.replace(
            config.denoise, grouped_wiener=True, grouped_wiener_passes=args.grouped_wiener_passes))
    if args.noisy_detail is not None:
        config = dataclasses.replace(config, splat=dataclasses.replace(config.splat, noisy_detail=args.noisy_detail))
    if args.pd_stride is not None:
        config = dataclasses.replace(config, denoise=dataclasses.replace(config.denoise, pd_stride=args.pd_stride))
    if args.noise_model != "auto":
        config = dataclasses.replace(config, denoise=dataclasses.replace(config.denoise, noise_model=args.noise_model))
    if args.pass_clean_below is not None:
        config = dataclasses.replace(config, denoise=dataclasses.replace(config.denoise,
                                                                         pass_clean_below_255=args.pass_clean_below))
    if args.rounds is not None:
        config = dataclasses.replace(config, rounds=args.rounds)
    result = run_pipeline(args.images_dir, args.out, config, force=args.force)
    print(f"report: {result.report_md}")
    return 0


#: `--noise-model`'s choices: the denoisers' models ("auto" here: as the photos' noise is found).
NOISE_MODEL_CHOICES = NOISE_MODELS
NOISE_MODEL_HELP = ("how the denoisers read each photo's noise level: auto (default) as the photos' noise is found "
                    "(on the luma where it is chroma-subsampled, as a JPEG's; else on the colour patches, with a "
                    "per-intensity curve where shot noise dominates); constant, curve or luma to force one. A "
                    "camera's JPEGs whose noise is too faint in the colour patches to be found (quality 80 and "
                    "under, or a clipped black background) are denoised with --pd-stride 2 --noise-model luma")


PASS_CLEAN_HELP = ("extension, not in the paper: round 1 passes the photos through undenoised, training no network, "
                   "when every photo's noise level reads under LEVEL/255 and nothing suggests noise the level misses "
                   "(a camera's JPEG); clean photos read 0.5-1.0/255, sigma 25/255 reads 23-26. 0 = always denoise. "
                   f"Default: the preset's ({PASS_CLEAN_BELOW_255:g} with default, best and fast)")


PD_STRIDE_HELP = ("extension, not in the paper: round 1 denoises pixel-shuffled sub-images of every N-th pixel, for "
                  "noise correlated between neighbouring pixels as a camera's demosaicing leaves it "
                  "(denoise.pixel_shuffle). 0 = measured from the photos (1 for independent noise), 1 = off, 2-4 = "
                  "that stride. Default: 0")


def _allow_focal_prior(config):
    from eval.evaluate import FOCAL_PRIOR_OK

    return dataclasses.replace(config, align=dataclasses.replace(config.align, max_focal_log_std=FOCAL_PRIOR_OK))


#: Modules a run of `denoise-gs eval` / a point of `denoise-gs cost` imports: the Ray workers import them
#: as the cluster starts (`eval.distributed.ray_cluster`).
EVAL_PRELOAD = ("eval.evaluate",)
COST_PRELOAD = ("eval.cost",)

def _training_views(kind: str, source: Path | str, size_wh: tuple[int, int] | None, scene_views: int | None) -> int:
    """How many training views the evaluated dataset has, known before any output is written: a dataset
    folder's split, or the split a scene will be rendered with (`--size`, `--scene-views`)."""
    if kind == "dataset":
        return len(validate_dataset_folder(Path(source)).train)
    from data_synth.rigs import rig_views, split_views  # data_synth imports open3d: scenes only
    from data_synth.scene_file import load_scene

    spec = load_scene(source, size_wh=size_wh, views=scene_views)
    return len(split_views([v.name for v in rig_views(spec.rig)], spec.split)["train"])


def _check_training_views(kind: str, source: Path | str, args: argparse.Namespace, command: str, *,
                          views: int | None) -> int:
    """`_training_views`, refused up front (before `--out` is written) when they are fewer than two, or than
    `views` (the `--views` given) asks for."""
    dataset = kind == "dataset"
    n = _training_views(kind, source, None if dataset else args.size, None if dataset else args.scene_views)
    where = Path(source) / "split.json" if dataset else None
    what = "the dataset's split" if dataset else (
        f"the scene rendered with {args.scene_views if args.scene_views is not None else 'its own number of'} "
        "views")
    more = "list more training views in split.json" if dataset else "render more views with --scene-views"
    if n < 2:
        raise InputError(f"{command} needs at least 2 training views; {what} has {n}", path=where, fix=more)
    if views is not None and views > n:
        raise InputError(f"--views {views} asks for more views than the {n} training views {what} has",
                         path=where, fix=f"pass --views of 2..{n}, or {more}")
    return n


def _prepare_out(args: argparse.Namespace, command: str, kind: str, source: Path | str):
    return prepare_output(args.out, command=command, inputs=[source if kind != "builtin" else None], resume=True)


def _cmd_eval(args: argparse.Namespace) -> int:
    device = str(resolve_device(args.device))
    kind, source = resolve_scene_source(args.scene)
    if kind == "dataset" and (args.size is not None or args.scene_views is not None):
        given = " and ".join(o for o, v in (("--size", args.size), ("--scene-views", args.scene_views))
                             if v is not None)
        verb = "apply" if args.size is not None and args.scene_views is not None else "applies"
        raise InputError(f"{given} {verb} to a scene rendered on the fly; this is a dataset folder, whose images "
                         "and views are used as they are", path=source,
                         fix="leave them out (--max-size downscales the dataset's images)")
    _check_training_views(kind, source, args, "denoise-gs eval", views=args.views)
    plan = _prepare_out(args, "denoise-gs eval", kind, source)
    methods = list(args.methods)
    if args.gt_pose_variants:
        methods += [m + GT_POSES_SUFFIX for m in args.methods
                    if m in METHODS and not METHODS[m].ground_truth_poses]
    config = EvalConfig(methods=tuple(dict.fromkeys(methods)), seeds=args.seeds, first_seed=args.first_seed,
                        preset=args.preset,
                        views=args.views, pose_fit_iters=args.pose_fit_iters, splat_iters=args.splat_iters,
                        device=device, allow_focal_prior=not args.strict_focal, denoiser=args.denoiser,
                        grouped_wiener=args.grouped_wiener, grouped_wiener_passes=args.grouped_wiener_passes,
                        noisy_detail=args.noisy_detail, pd_stride=args.pd_stride,
                        noise_model=None if args.noise_model == "auto" else args.noise_model,
                        pass_clean_below=args.pass_clean_below)
    cluster = _cluster_settings(args, device)
    out = Path(args.out)
    with (resumable_output_dir(plan), output_lock(out),
          ray_cluster(cluster, preload=EVAL_PRELOAD, tasks=len(config.methods) * config.seeds) as executor):
        name, folder = scene_dataset(kind, source, out, size_wh=args.size, views=args.scene_views)
        given = validate_dataset_folder(folder)
        if any(m.endswith(GT_POSES_SUFFIX) or (m in METHODS and METHODS[m].ground_truth_poses)
               for m in config.methods):  # these splat with the true cameras
            check_renderable_cameras(given)
        dataset = validate_dataset_folder(working_dataset(folder, out, args.max_size))
        title = f"denoise-gs eval: {name}"
        settings = _eval_settings(config, dataset.root, name, args)
        earlier = carried_rows(out, settings, {(name, m, s) for m in config.methods for s in config.seed_values})
        if earlier.note:
            _log.warning("%s", earlier.note)
        rows = evaluate_dataset(dataset, out, config, scene=name, executor=executor,
                                on_row=lambda rs: write_results(out, merge_rows(earlier.rows, rs),
                                                                title=title + " (in progress)", settings=settings))
        _, md = write_results(out, merge_rows(earlier.rows, rows), title=title, settings=settings)
    kept = sorted({r.method for r in earlier.rows})
    print(f"results: {md}" + (f" (with the earlier rows of {', '.join(kept)})" if kept else ""))
    if rows and all(r.error for r in rows):  # a table of n/a cells is not a result: say so in the exit status
        print(f"error: every run of this evaluation failed ({len(rows)}); the first: {rows[0].method}, seed "
              f"{rows[0].seed}: {rows[0].error.splitlines()[0][:300]}\n  the reasons: {md}", file=sys.stderr)
        return 1
    return 0


def _eval_settings(config: EvalConfig, dataset_root: Path, scene: str, args: argparse.Namespace) -> dict:
    """What makes the rows of two `denoise-gs eval` invocations into one folder comparable: the dataset's
    files, every setting but the methods and seeds, and the project code (`eval.results.carried_rows`)."""
    from eval.distributed import project_code
    from eval.pipeline.hashing import hash_json, hash_path

    kept = {k: v for k, v in dataclasses.asdict(config).items() if k not in ("methods", "seeds", "first_seed")}
    return {"scene": scene, "dataset": hash_path(dataset_root), "max_size": args.max_size,
            "code": hash_json(project_code()), **kept}


def _parse_grid(items: Sequence[str] | None, knobs: Sequence[str] | None) -> dict[str, tuple]:
    """`--knobs` (subset of the default grid) and `--grid KNOB=V1,V2,...` overrides -> grid."""
    from eval.cost import DEFAULT_GRID, KNOBS

    for k in knobs or ():
        if k not in DEFAULT_GRID:
            raise InputError(f"unknown knob {k!r}", fix=f"choose from {', '.join(DEFAULT_GRID)}")
    grid = {k: DEFAULT_GRID[k] for k in knobs} if knobs else dict(DEFAULT_GRID)
    for item in items or ():
        knob, _, values = item.partition("=")
        if knob not in KNOBS or not values:
            raise InputError(f"bad --grid {item!r}", fix=f"write KNOB=V1,V2 with KNOB one of {', '.join(KNOBS)}")
        vals = tuple(v.strip() for v in values.split(",") if v.strip())
        if knob != "preset":
            try:
                vals = tuple(int(v) for v in vals)
            except ValueError:
                raise InputError(f"--grid {knob} needs integers, got {values!r}") from None
            if any(v < 1 for v in vals):
                raise InputError(f"--grid {knob} values must be >= 1, got {values!r}")
        else:
            for v in vals:
                preset(v)
        grid[knob] = vals
    return grid


def _cmd_cost(args: argparse.Namespace) -> int:
    from eval.cost import CostConfig, run_cost_sweep, sweep_points, write_cost_results

    device = str(resolve_device(args.device))
    kind, source = resolve_scene_source(args.scene)
    grid = _parse_grid(args.grid, args.knobs)
    n_train = _check_training_views(kind, source, args, "the cost sweep", views=None)  # K is capped to them
    asked = [v for v in grid.get("train_views", ()) if v > n_train]
    if asked and any(item.partition("=")[0] == "train_views" for item in args.grid or ()):
        raise InputError(f"--grid train_views={','.join(map(str, asked))} asks for more training views than "
                         f"the dataset has ({n_train})", path=Path(source) / "split.json" if kind == "dataset"
                         else None, fix=f"use train_views values of 2..{n_train}")
    plan = _prepare_out(args, "denoise-gs cost", kind, source)
    base = preset(args.preset, rounds=args.rounds, views=args.views, seed=args.seed, device=device)
    base = dataclasses.replace(base, max_size=None)  # the sweep scores against clean images at their own size
    if not args.strict_focal:
        base = _allow_focal_prior(base)
    points = sweep_points(base, grid)  # bad values fail here, before any compute
    config = CostConfig(base=base, grid=grid, pose_fit_iters=args.pose_fit_iters)
    cluster = _cluster_settings(args, device)
    out = Path(args.out)
    with (resumable_output_dir(plan), output_lock(out),
          ray_cluster(cluster, preload=COST_PRELOAD, tasks=len(points)) as executor):
        name, folder = scene_dataset(kind, source, out, size_wh=args.size if kind != "dataset" else None,
                                     views=args.scene_views if kind != "dataset" else None)
        dataset = validate_dataset_folder(folder)
        base = dataclasses.replace(base, views=min(base.views, len(dataset.train)))
        try:
            rows = run_cost_sweep(dataset, out, dataclasses.replace(config, base=base), executor=executor)
        except (DisconnectedViewsError, AlignmentRefusedError) as exc:
            if kind == "dataset":
                raise
            raise _rendered_views_refusal(exc, args) from None
        _, md = write_cost_results(out, rows, title=f"denoise-gs cost: {name}")
    print(f"results: {md}")
    return 0


def _rendered_views_refusal(exc: DisconnectedViewsError | AlignmentRefusedError, args: argparse.Namespace):
    """An alignment refusal of a scene the command rendered (a built-in name or a scene file): the pipeline's
    fix (leave photos out of the input folder, add photos) becomes the options that render the views."""
    w, h = args.size
    fix = (f"the scene's {args.scene_views} views rendered at {w}x{h} cannot all be related: render them larger "
           "(--size) or more of them (--scene-views), or pass a dataset folder")
    if isinstance(exc, DisconnectedViewsError):
        return DisconnectedViewsError(exc.message, views=exc.views, path=exc.path, fix=fix)
    return exc.with_fix(fix)


def _cluster_settings(args: argparse.Namespace, device: str) -> ClusterSettings:
    """`--workers` / `--ray-address` -> where the tasks run (checked here, before any output is written).
    On CUDA the tasks of a local cluster share the GPU; on a cluster each takes one."""
    gpus = 0.0 if not device.startswith("cuda") else 1.0 if args.ray_address else 1.0 / args.workers
    settings = ClusterSettings(workers=args.workers, address=args.ray_address, gpus_per_task=gpus,
                               task_threads=args.task_threads)
    if settings.address is not None:
        check_ray_address(settings.address)
    return settings


WORKERS_HELP = ("runs at once: 1 (default) runs them one after another here; N > 1 starts a local Ray cluster "
                "of N CPUs, one run per CPU (docs/cluster.md)")
TASK_THREADS_HELP = ("with --workers or --ray-address: torch and compositor threads per run (default: the run's "
                     "one CPU); the scores are the serial run's with any value (docs/cluster.md, \"Threads and "
                     "memory per task\")")
RAY_ADDRESS_HELP = ("run on an existing Ray cluster instead: its head's host:port (as `ray start --head` prints), "
                    "or auto; the out folder must be at the same path on every node (docs/cluster.md)")


def _size_wh(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 256x192, got {text!r}") from None
    if w < 32 or h < 32:
        raise argparse.ArgumentTypeError(f"images must be at least 32x32, got {text!r}")
    if max(w, h) > 8192:  # the scene renderer's limit (data_synth RenderSpec.size)
        raise argparse.ArgumentTypeError(f"images must be at most 8192 px a side, got {text!r}")
    return w, h


MAX_SIZE_HELP = ("long side in pixels of the working images (default 512): larger photos are downscaled once "
                 "(area filter); 0 keeps the input size")


def _max_size(text: str) -> int | None:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of pixels, got {text!r}") from None
    if n == 0:
        return None
    if n < MIN_IMAGE_SIZE_PX:
        raise argparse.ArgumentTypeError(f"must be 0 (input size) or at least {MIN_IMAGE_SIZE_PX}, got {n}")
    return n


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="denoise-gs",
        description="Denoise-GS: poses, a denoised Gaussian-splat scene and clean novel views from a dozen "
                    "noisy, unposed photos; and its evaluation.")
    add_common_args(parser)
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run the pipeline (denoise, align, splat; one round, --rounds 2 for the "
                                     "paper's second) on a folder of noisy images")
    run.add_argument("images_dir", type=Path,
                     help="folder of noisy images (PNG/JPEG/TIFF/WebP; HEIC and raw photos: convert them first)")
    run.add_argument("--out", type=out_path, required=True, help=OUT_RESUME_HELP)
    run.add_argument("--preset", choices=sorted(PRESETS), default="default",
                     help="settings preset: fast (N2V, a 1000-iteration splat; make demo's), default (R2R or "
                          "Neighbor2Neighbor with the Wiener steps, a 2000-iteration splat), best (default with "
                          "the UNet at width 32)")
    run.add_argument("--views", type=int_range(2), default=None,
                     help="K views kept for rounds >= 2 (default 12); needs at least K images")
    run.add_argument("--rounds", type=positive_int, default=None,
                     help="1 = round 1 only (every preset's); 2 adds the paper's second round (N2V only)")
    run.add_argument("--seed", type=seed, default=None, help="master seed (default 0)")
    run.add_argument("--device", default=None, help=DEVICE_HELP + "; default cpu")
    run.add_argument("--max-size", type=_max_size, default=PipelineConfig().max_size, metavar="N",
                     help=MAX_SIZE_HELP)
    run.add_argument("--denoiser", choices=DENOISE_METHODS, default=None,
                     help="round 1's self-supervised objective on the UNet (default: the preset's: auto with "
                          "default and best, R2R unless over a fifth of the photos' area (mean over the photos) "
                          "is black and clipped, then "
                          "neighbor2neighbor; n2v with fast; only n2v runs more than one round)")
    run.add_argument("--keep-noisy", type=half_open_fraction, default=None, metavar="K",
                     help="fraction of the noisy photo kept in round 1's photos, (1 - K) * denoised + K * noisy, "
                          "0 <= K < 1 (the splat averages the noise across views, not the blur). Default: the "
                          "preset's")
    run.add_argument("--wiener", action=argparse.BooleanOptionalAction, default=None,
                     help="refine round 1's denoised photos with the sliding-window DCT Wiener step (the noisy "
                          "photo shrunk by the gains the network's output implies; denoise.wiener). Default: the "
                          "preset's")
    run.add_argument("--grouped-wiener", action=argparse.BooleanOptionalAction, default=None,
                     help="then the grouped Wiener step (similar patches of the noisy photo filtered together with "
                          "the statistics of the photo so far; denoise.grouped_wiener; about 1.5 s per 384x384 photo "
                          "on 2 cores). Default: the preset's")
    run.add_argument("--grouped-wiener-passes", type=positive_int, default=None, metavar="N",
                     help="run the grouped Wiener step N times (turns it on), each pass with the previous one's "
                          "output as its pilot and 80 patches per group after the first: +0.14 to +0.28 dB on the "
                          "photos of four real sets with N = 2, at 5-6 s more per 384x384 photo on 2 cores. "
                          "Default: the preset's (1)")
    run.add_argument("--noisy-detail", type=fraction, default=None, metavar="W",
                     help="extension, not in the paper: the fraction W of the noisy photo's finest band that the "
                          "splat's target takes back, denoised + W * highpass(noisy - denoised) (the splat keeps "
                          "the texture every view shows and averages the noise; denoise.detail). 0 = off. "
                          "Default: the preset's (0.2 with default and best, 0.5 with fast)")
    run.add_argument("--pd-stride", type=int_range(0, MAX_STRIDE), default=None, metavar="N", help=PD_STRIDE_HELP)
    run.add_argument("--noise-model", choices=NOISE_MODEL_CHOICES, default="auto", help=NOISE_MODEL_HELP)
    run.add_argument("--pass-clean-below", type=nonneg_float, default=None, metavar="LEVEL", help=PASS_CLEAN_HELP)
    run.add_argument("--no-select", action="store_true", help="rounds >= 2 use every view (ablation)")
    run.add_argument("--force", action="store_true", help="re-run stages even when their outputs are complete")
    run.add_argument("--allow-focal-prior", action="store_true",
                     help="when the views do not determine the focal length, go on with the prior instead of "
                          "stopping (as `denoise-gs eval` does; check the result's poses)")
    run.add_argument("--fuse-noisy-splat", action=argparse.BooleanOptionalAction, default=None,
                     help="extension, not in the paper: each round's splat trains on the mean of the denoised "
                          "photo and the render of a splat of the noisy photos (one more splat per round). "
                          "Default: off in every preset (the splat takes the noisy photos' finest band "
                          "instead: --noisy-detail)")
    run.add_argument("--reuse-intrinsics", choices=("auto", "always", "never"), default=None,
                     help="rounds >= 2: auto (default) keeps the better-determined of the round's own focal "
                          "estimate and the previous round's; always takes the previous round's; never "
                          "estimates anew each round (the paper's loop)")
    run.add_argument("--align-photos", choices=ALIGN_PHOTOS, default=None,
                     help="round 1's alignment input: the noisy photos, and the denoised ones where those are "
                          "refused (noisy_first); both, keeping the alignment whose camera centres are better "
                          "determined (better_of); or the denoised ones (the paper's). Default: the preset's "
                          "(better_of with default and best, denoised with fast)")
    run.add_argument("--intrinsics", type=Path, default=None, metavar="FILE",
                     help="the photos' calibration at their size: a COLMAP cameras.txt with one camera, or an "
                          "mrcal .cameramodel, without lens distortion (undistort the photos first). Every "
                          "round's alignment uses it instead of estimating the focal length")
    run.set_defaults(func=_cmd_run)

    ev = sub.add_parser("eval", help="score methods on a scene with ground truth")
    ev.add_argument("scene", help="built-in data_synth scene, scene .toml, or dataset folder "
                                  "(images/, clean/, split.json, sparse/0/)")
    ev.add_argument("--out", type=out_path, required=True, help=OUT_RESUME_HELP)
    ev.add_argument("--seeds", type=positive_int, default=3, help="seeds per method (default 3)")
    ev.add_argument("--first-seed", type=seed, default=0, metavar="K",
                    help="the seeds are K .. K + seeds - 1 (default 0): runs an evaluation seed by seed, each "
                         "into its own folder or, with the same code and settings, into one (its table "
                         "keeps the earlier seeds' rows)")
    ev.add_argument("--methods", nargs="+", default=["instantsplat", "nlm_instantsplat", "n2v_round1",
                                                     "denoise_gs"], metavar="METHOD",
                    help="any of: " + "; ".join(f"{m.name}: {m.description}" for m in METHODS.values()
                                                if m.gt_pose_variant_of is None)
                    + f"; and METHOD{GT_POSES_SUFFIX} for any with estimated poses: the photos its splat trained "
                      "on, splatted with the ground-truth cameras")
    ev.add_argument("--gt-pose-variants", action="store_true",
                    help=f"add METHOD{GT_POSES_SUFFIX} for each method given: the denoising's effect apart from "
                         "the pose error")
    ev.add_argument("--preset", choices=sorted(PRESETS), default="default")
    ev.add_argument("--views", type=int_range(2), default=None,
                    help="K for rounds >= 2 (default min(12, training views))")
    ev.add_argument("--pose-fit-iters", type=nonneg_int, default=None, help="held-out pose refinement steps")
    ev.add_argument("--splat-iters", type=positive_int, default=None,
                    help="splat training iterations of every method (default: the preset's for product and "
                         "oracle_clean, InstantSplat's 1000 for the baselines and the paper's loop)")
    ev.add_argument("--device", default="cpu", help=DEVICE_HELP + "; default cpu")
    ev.add_argument("--denoiser", choices=DENOISE_METHODS, default="n2v",
                    help="round 1's objective for the N2V methods (default n2v; others: one-round methods only)")
    ev.add_argument("--grouped-wiener", action=argparse.BooleanOptionalAction, default=None,
                    help="the grouped Wiener step on or off for every method that trains the UNet (default: the "
                         "preset's; an A/B comparison evaluates each setting into its own --out)")
    ev.add_argument("--grouped-wiener-passes", type=positive_int, default=None, metavar="N",
                    help="passes of the grouped Wiener step for every method that trains the UNet (see `run "
                         "--grouped-wiener-passes`; an A/B comparison evaluates each setting into its own --out)")
    ev.add_argument("--noisy-detail", type=fraction, default=None, metavar="W",
                    help="the noisy photos' band in the product's splat target (see `run --noisy-detail`; the "
                         "paper's loop, the baselines and the oracle train on their photos as they are). "
                         "Default: the preset's")
    ev.add_argument("--pd-stride", type=int_range(0, MAX_STRIDE), default=None, metavar="N",
                    help="round 1's pixel-shuffle stride for every method that trains the UNet (see `run "
                         "--pd-stride`; an A/B comparison evaluates each setting into its own --out)")
    ev.add_argument("--noise-model", choices=NOISE_MODEL_CHOICES, default="auto",
                    help="the denoisers' noise model for every method that trains the UNet (see `run "
                         "--noise-model`)")
    ev.add_argument("--pass-clean-below", type=nonneg_float, default=None, metavar="LEVEL",
                    help="round 1's pass-through level for the methods that take the preset's (see `run "
                         "--pass-clean-below`; the paper's loop always denoises)")
    ev.add_argument("--max-size", type=_max_size, default=PipelineConfig().max_size, metavar="N",
                    help=MAX_SIZE_HELP + " (the clean images and ground-truth cameras are scaled alike)")
    ev.add_argument("--size", type=_size_wh, default=None, metavar="WxH",
                    help="image size for a scene rendered on the fly (default: the scene's)")
    ev.add_argument("--scene-views", type=int_range(2), default=None,
                    help="number of views for a scene rendered on the fly (default: the scene's)")
    ev.add_argument("--strict-focal", action="store_true",
                    help="alignment refuses an undetermined focal length (default: keep the prior, as "
                         "InstantSplat does, and let the scores show the cost)")
    ev.add_argument("--workers", type=positive_int, default=1, metavar="N", help=WORKERS_HELP)
    ev.add_argument("--ray-address", default=None, metavar="ADDR", help=RAY_ADDRESS_HELP)
    ev.add_argument("--task-threads", type=positive_int, default=None, metavar="N", help=TASK_THREADS_HELP)
    ev.set_defaults(func=_cmd_eval)

    cost = sub.add_parser("cost", help="accuracy-time trade-off sweep on a scene",
                          description="Change one pipeline knob at a time from a base configuration and report "
                                      "held-out PSNR / pose error against wall time per stage and end to end.")
    cost.add_argument("scene", help="built-in data_synth scene, scene .toml, or dataset folder")
    cost.add_argument("--out", type=out_path, required=True, help=OUT_RESUME_HELP + " (cached stages are reused)")
    cost.add_argument("--size", type=_size_wh, default=(128, 96), metavar="WxH",
                      help="image size for a scene rendered on the fly (default 128x96: a sweep in minutes)")
    cost.add_argument("--scene-views", type=int_range(2), default=10,
                      help="views rendered for a scene (default 10: 8 training + 2 held-out for llff_like)")
    cost.add_argument("--preset", choices=sorted(PRESETS), default="fast", help="base configuration's preset")
    cost.add_argument("--rounds", type=positive_int, default=1, help="rounds of the base configuration (default 1)")
    cost.add_argument("--views", type=int_range(2), default=8, help="K for rounds >= 2 (default 8)")
    cost.add_argument("--seed", type=seed, default=0)
    cost.add_argument("--device", default="cpu", help=DEVICE_HELP + "; default cpu")
    cost.add_argument("--knobs", nargs="+", default=None, metavar="KNOB",
                      help="sweep only these knobs (default all: n2v_steps passes align_iters align_size align_points "
                           "splat_iters views train_views preset)")
    cost.add_argument("--grid", action="append", default=None, metavar="KNOB=V1,V2",
                      help="values of one knob (repeatable), e.g. --grid splat_iters=100,300")
    cost.add_argument("--pose-fit-iters", type=nonneg_int, default=None, help="held-out pose refinement steps")
    cost.add_argument("--strict-focal", action="store_true", help="as for eval")
    cost.add_argument("--workers", type=positive_int, default=1, metavar="N", help=WORKERS_HELP)
    cost.add_argument("--ray-address", default=None, metavar="ADDR", help=RAY_ADDRESS_HELP)
    cost.add_argument("--task-threads", type=positive_int, default=None, metavar="N", help=TASK_THREADS_HELP)
    cost.set_defaults(func=_cmd_cost)
    add_dataset_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point `denoise-gs`."""
    parser = build_parser()
    return run_cli(lambda args: args.func(args), parser, argv)
