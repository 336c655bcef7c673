"""Logging set-up shared by the CLIs."""

from __future__ import annotations

import logging
import sys


def setup_logging(verbosity: int = 0) -> None:
    """0: warnings and stage summaries (INFO of our packages), 1+: DEBUG."""
    level = logging.DEBUG if verbosity > 0 else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname).1s %(name)s: %(message)s", "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING)
    for pkg in ("mvgeo", "splat", "denoise", "eval", "data_synth"):
        logging.getLogger(pkg).setLevel(level)
