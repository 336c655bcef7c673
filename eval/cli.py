"""`denoise-gs run | eval | cost`: the product's command line (thin: parse, validate, call the library).

Every input problem is reported before any compute, with exit code 2.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
from collections.abc import Sequence
from pathlib import Path

from eval.evaluate import EVAL_METHODS, EvalConfig, evaluate_dataset, scene_dataset
from eval.pipeline import PRESETS, preset, run_pipeline, validate_dataset_folder
from eval.pipeline.components import require
from eval.pipeline.lock import output_lock
from eval.results import write_results
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.errors import DgsError, InputError

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
    config = preset(args.preset, views=args.views, rounds=args.rounds, seed=args.seed,
                    select_views=False if args.no_select else None, device=args.device)
    result = run_pipeline(args.images_dir, args.out, config, force=args.force)
    print(f"report: {result.report_md}")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    kind, source = resolve_scene_source(args.scene)
    config = EvalConfig(methods=tuple(dict.fromkeys(args.methods)), seeds=args.seeds, preset=args.preset,
                        views=args.views, pose_fit_iters=args.pose_fit_iters, splat_iters=args.splat_iters,
                        device=args.device)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", path=out, fix="choose another --out")
    if kind != "dataset":
        require("data_synth", "render_scene", needed_for="denoise-gs eval on a scene")
    with output_lock(out):
        name, folder = scene_dataset(kind, source, out, size_wh=args.size, views=args.scene_views)
        dataset = validate_dataset_folder(folder)
        rows = evaluate_dataset(dataset, out, config, scene=name)
        _, md = write_results(out, rows, title=f"denoise-gs eval: {name}")
    print(f"results: {md}")
    return 0


def _cmd_cost(args: argparse.Namespace) -> int:
    resolve_scene_source(args.scene)
    raise DgsError("denoise-gs cost: the accuracy-time sweep is not implemented yet; the inputs were validated.")


def _size_wh(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 256x192, got {text!r}") from None
    if w < 32 or h < 32:
        raise argparse.ArgumentTypeError(f"images must be at least 32x32, got {text!r}")
    return w, h


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="denoise-gs",
        description="Denoise-GS: poses, a denoised Gaussian-splat scene and clean novel views from a dozen "
                    "noisy, unposed photos; and its evaluation.")
    add_common_args(parser)
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run the two-round pipeline on a folder of noisy images")
    run.add_argument("images_dir", type=Path, help="folder of noisy images (PNG/JPEG/TIFF)")
    run.add_argument("--out", type=Path, required=True, help="output folder (resumable)")
    run.add_argument("--preset", choices=sorted(PRESETS), default="default", help="settings preset")
    run.add_argument("--views", type=int, default=None,
                     help="K views kept for rounds >= 2 (default 12); needs at least K images")
    run.add_argument("--rounds", type=int, default=None, help="1 = round 1 only; default 2")
    run.add_argument("--seed", type=int, default=None, help="master seed (default 0)")
    run.add_argument("--device", default=None, help="torch device, e.g. cpu or cuda (default cpu)")
    run.add_argument("--no-select", action="store_true", help="rounds >= 2 use every view (ablation)")
    run.add_argument("--force", action="store_true", help="re-run stages even when their outputs are complete")
    run.set_defaults(func=_cmd_run)

    ev = sub.add_parser("eval", help="score methods on a scene with ground truth")
    ev.add_argument("scene", help="built-in data_synth scene, scene .toml, or dataset folder "
                                  "(images/, clean/, split.json, sparse/0/)")
    ev.add_argument("--out", type=Path, required=True)
    ev.add_argument("--seeds", type=int, default=3)
    ev.add_argument("--methods", nargs="+", default=["instantsplat", "nlm_instantsplat", "n2v_round1",
                                                     "denoise_gs"], metavar="METHOD",
                    help=f"any of: {', '.join(EVAL_METHODS)}")
    ev.add_argument("--preset", choices=sorted(PRESETS), default="default")
    ev.add_argument("--views", type=int, default=None, help="K for rounds >= 2 (default min(12, training views))")
    ev.add_argument("--pose-fit-iters", type=int, default=None, help="held-out pose refinement steps")
    ev.add_argument("--splat-iters", type=int, default=None, help="splat training iterations (all methods)")
    ev.add_argument("--device", default="cpu")
    ev.add_argument("--size", type=_size_wh, default=None, metavar="WxH",
                    help="image size for a scene rendered on the fly (default: the scene's)")
    ev.add_argument("--scene-views", type=int, default=None,
                    help="number of views for a scene rendered on the fly (default: the scene's)")
    ev.set_defaults(func=_cmd_eval)

    cost = sub.add_parser("cost", help="accuracy-time trade-off sweep on a scene")
    cost.add_argument("scene")
    cost.add_argument("--out", type=Path, required=True)
    cost.set_defaults(func=_cmd_cost)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point `denoise-gs`."""
    parser = build_parser()
    return run_cli(lambda args: args.func(args), parser, argv)
