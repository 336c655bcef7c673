"""`data-synth`: list, show and render synthetic scenes.

    data-synth list
    data-synth show SCENE [--seed N] [--size WxH] [--views N]
    data-synth render SCENE --out DIR [--seed N] [--size WxH] [--views N]
    data-synth effects
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence

from data_synth.dataset import write_dataset
from data_synth.effects import EFFECTS
from data_synth.scene_file import builtin_scenes, load_scene, scene_to_toml
from mvgeo.common.cli import add_common_args, run_cli
from mvgeo.common.errors import InputError


def parse_size(text: str) -> tuple[int, int]:
    """'504x378' -> (504, 378).

    Raises:
        InputError: not WxH with positive integers.
    """
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise InputError(f"bad --size {text!r}", fix="write it as WIDTHxHEIGHT, e.g. --size 504x378")
    return int(m.group(1)), int(m.group(2))


def _add_overrides(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="built-in scene name (see `data-synth list`) or a .toml file")
    p.add_argument("--seed", type=int, default=None, help="seed of the effects' random streams")
    p.add_argument("--size", default=None, help="image size WxH (field of view kept), e.g. 504x378")
    p.add_argument("--views", type=int, default=None, help="number of views")


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
    render.add_argument("--out", required=True, help="output dataset folder (replaced when complete)")
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
    if args.views is not None and args.views < 1:
        raise InputError(f"--views must be >= 1, got {args.views}")
    if args.seed is not None and not 0 <= args.seed < 2**32:
        raise InputError(f"--seed must be in [0, 2^32), got {args.seed}")
    size = parse_size(args.size) if args.size is not None else None
    spec = load_scene(args.scene, seed=args.seed, size_wh=size, views=args.views)
    if args.command == "show":
        sys.stdout.write(scene_to_toml(spec))
        return 0
    out = write_dataset(spec, args.out)
    print(out)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_main, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
