"""Console entry points: import the command's module, then run its `main`.

The command modules import torch, OpenCV and open3d when they load (seconds). The
console scripts call these functions instead of the modules' `main` directly, so a
Ctrl-C while they load ends with one line on stderr and exit code 130, as it does
while a command runs (`mvgeo.common.cli.run_cli`), not with a traceback.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

__all__ = ["data_synth", "denoise", "denoise_gs", "mvgeo", "splat"]

#: The exit code of a command interrupted by Ctrl-C (128 + SIGINT), as `run_cli` returns it.
EXIT_INTERRUPTED = 130


def _launch(module: str, argv: Sequence[str] | None) -> int:
    try:
        main = importlib.import_module(module).main
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return main(argv)


def denoise_gs(argv: Sequence[str] | None = None) -> int:
    """`denoise-gs` (`eval.cli.main`)."""
    return _launch("eval.cli", argv)


def mvgeo(argv: Sequence[str] | None = None) -> int:
    """`mvgeo` (`mvgeo.cli.main`)."""
    return _launch("mvgeo.cli", argv)


def splat(argv: Sequence[str] | None = None) -> int:
    """`splat` (`splat.cli.main`)."""
    return _launch("splat.cli", argv)


def denoise(argv: Sequence[str] | None = None) -> int:
    """`denoise` (`denoise.cli.main`)."""
    return _launch("denoise.cli", argv)


def data_synth(argv: Sequence[str] | None = None) -> int:
    """`data-synth` (`data_synth.cli.main`)."""
    return _launch("data_synth.cli", argv)
