"""What every console script shares: argument parsing glue, logging, and
turning `InputError` into a one-paragraph message with exit code 2."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence

from mvgeo.common.errors import DgsError, InputError
from mvgeo.common.log import setup_logging

EXIT_INPUT_ERROR = 2
EXIT_FAILURE = 1


def add_common_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-v: debug)")


def run_cli(main: Callable[[argparse.Namespace], int | None], parser: argparse.ArgumentParser,
            argv: Sequence[str] | None = None) -> int:
    """Parse `argv`, set up logging, run `main(args)` and map errors to exit codes.

    - `InputError` (bad files, keys, values): message on stderr, no traceback, exit 2.
    - other `DgsError` (e.g. degenerate geometry the user must know about): message, exit 1.
    - argparse usage errors exit 2 (argparse's own behaviour).
    """
    args = parser.parse_args(argv)
    setup_logging(getattr(args, "verbose", 0))
    try:
        code = main(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT_ERROR
    except DgsError as exc:
        logging.getLogger(__name__).debug("failure", exc_info=True)
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(code or 0)
