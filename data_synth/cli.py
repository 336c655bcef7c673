"""`data-synth`: list, show and render synthetic scenes.

    data-synth list
    data-synth show SCENE [--seed N] [--size WxH] [--views N]
    data-synth render SCENE --out DIR [--seed N] [--size WxH] [--views N]
    data-synth effects
"""

from __future__ import annotations

from mvgeo.common.threads import apply_thread_policy

# Before the imports below load torch: OpenMP reads OMP_WAIT_POLICY once, when it loads
# (mvgeo.common.threads.apply_thread_policy; docs/conventions.md, "Threads").
apply_thread_policy()

import argparse
import dataclasses
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from data_synth.dataset import DATASET_COMMAND, write_dataset
from data_synth.effects import EFFECTS
from data_synth.scene_file import builtin_scenes, load_scene, scene_to_toml
from data_synth.spec import RenderSpec
from mvgeo.common.argtypes import out_path, positive_int, seed, size_wh
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.errors import InputError
from mvgeo.common.output import OUT_HELP, OVERWRITE_HELP, prepare_output


def parse_size(text: str) -> tuple[int, int]:
    """'504x378' -> (504, 378).

    Raises:
        InputError: not WxH with positive integers.
    """
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise InputError(f"bad --size {text!r}", fix="write it as WIDTHxHEIGHT, e.g. --size 504x378")
    return int(m.group(1)), int(m.group(2))


#: (smallest, largest) image side in pixels, as `[render] size` accepts it.
_SIZE_RANGE_PX = {f.name: f for f in dataclasses.fields(RenderSpec)}["size"].metadata["range"]


def _add_overrides(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="built-in scene name (see `data-synth list`) or a .toml file")
    p.add_argument("--seed", type=seed, default=None, help="seed of the effects' random streams")
    p.add_argument("--size", type=size_wh(*_SIZE_RANGE_PX), default=None, metavar="WxH",
                   help="image size WxH (field of view kept), e.g. 504x378; each side "
                        f"{_SIZE_RANGE_PX[0]}..{_SIZE_RANGE_PX[1]} px")
    p.add_argument("--views", type=positive_int, default=None, help="number of views")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="data-synth", description=__doc__.splitlines()[0])
    add_common_args(parser)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="built-in scenes, one line each")
    sub.add_parser("effects", help="registered effects, one line each")
    show = sub.add_parser("show", help="print the resolved scene file")
    _add_overrides(show)
    render = sub.add_parser("render", help="render a scene into a dataset folder")
    _add_overrides(render)
    render.add_argument("--out", type=out_path, required=True, help="output dataset folder; " + OUT_HELP)
    render.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    return parser


def _main(args: argparse.Namespace) -> int:
    if args.command == "list":
        for name, path in builtin_scenes().items():
            spec = load_scene(path)
            w, h = spec.render.size
            fx = f"{len(spec.effects)} effect(s)" if spec.effects else "no effects"
            print(f"{name:20s} {spec.rig.num_views:3d} views {w}x{h}  {fx:13s} {spec.info.description}")
        return 0
    if args.command == "effects":
        for name, d in sorted(EFFECTS.items()):
            print(f"{name:18s} {d.summary}")
        return 0
    plan = None
    if args.command == "render":
        scene_file = args.scene if Path(args.scene).suffix == ".toml" or Path(args.scene).exists() else None
        plan = prepare_output(args.out, command=DATASET_COMMAND, inputs=[scene_file], overwrite=args.overwrite)
    spec = load_scene(args.scene, seed=args.seed, size_wh=args.size, views=args.views)
    if args.command == "show":
        sys.stdout.write(scene_to_toml(spec))
        return 0
    out = write_dataset(spec, plan)
    print(out)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_main, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
