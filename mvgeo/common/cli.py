"""What every console script shares: argument parsing glue, logging, and
turning `InputError` into a one-paragraph message with exit code 2.

SIGTERM (a job scheduler or `kill` stopping a run) raises `Terminated` in the
main thread while the command runs: the stack unwinds through the commands'
`with` blocks, so temporary output folders and locks are removed, and the
process exits with 143 (128 + SIGTERM) after a one-line message. pycolmap's
logging library replaces the SIGTERM handler with one that prints a native
stack dump when pycolmap is imported; `mvgeo.common.deps` puts the Python
handler back after that import.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import logging
import os
import select
import signal
import sys
import threading
from collections.abc import Callable, Sequence

from mvgeo.common.errors import DgsError, InputError
from mvgeo.common.log import setup_logging

EXIT_INPUT_ERROR = 2
EXIT_FAILURE = 1
EXIT_TERMINATED = 128 + signal.SIGTERM
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE


class Terminated(BaseException):
    """Raised in the main thread by SIGTERM while a command runs (a BaseException, so that
    `except Exception` in library code does not swallow it)."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated


def _install_sigterm_handler():
    """Install `_raise_terminated` for SIGTERM; returns the previous handler (None off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_terminated)


def _stdout_reader_gone() -> bool:
    """Whether stdout is a pipe whose reader has closed it (poll reports an error on the descriptor)."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no descriptor (a test's capture), or no poll
        return False


def _silence_stdout() -> None:
    """Point file descriptor 1 at /dev/null (after a broken pipe: nothing more can reach the reader)."""
    with contextlib.suppress(OSError, ValueError):  # ValueError: stdout without a descriptor (a test's capture)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)


def add_common_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-v: debug)")


def run_cli(main: Callable[[argparse.Namespace], int | None], parser: argparse.ArgumentParser,
            argv: Sequence[str] | None = None) -> int:
    """Parse `argv`, set up logging, run `main(args)` and map errors to exit codes.

    - `InputError` (bad files, keys, values): message on stderr, no traceback, exit 2.
    - other `DgsError` (e.g. degenerate geometry the user must know about): message, exit 1.
    - argparse usage errors exit 2 (argparse's own behaviour).
    - SIGTERM while `main` runs: one line on stderr, exit 143 (see the module docstring).
    - a full disk or quota (`OSError` ENOSPC / EDQUOT): one message (naming the file where the system gives
      it), no traceback, exit 1. The commands write their outputs atomically, so what the error interrupted
      is not left as a result.
    - stdout closed by its reader (`data-synth list | head -3`): quiet, exit 141 (128 + SIGPIPE), as a
      command killed by SIGPIPE would; stdout is pointed at /dev/null so the interpreter's final flush
      does not report the same broken pipe. A broken pipe while stdout is still read (a subprocess's, a
      socket's) is a failure and is raised.
    """
    args = parser.parse_args(argv)
    setup_logging(getattr(args, "verbose", 0))
    previous = _install_sigterm_handler()
    try:
        code = main(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT_ERROR
    except DgsError as exc:
        logging.getLogger(__name__).debug("failure", exc_info=True)
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except BrokenPipeError:
        if not _stdout_reader_gone():
            raise  # another pipe (a subprocess, a socket): a failure, not a reader that stopped
        _silence_stdout()
        return EXIT_BROKEN_PIPE
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        where = f" while writing {exc.filename}" if exc.filename else ""
        print(f"error: no space left (disk full or quota exceeded){where} ({exc.strerror})\n  fix: free some space, "
              "or write --out to another disk", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("terminated (SIGTERM)", file=sys.stderr)
        return EXIT_TERMINATED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return int(code or 0)
