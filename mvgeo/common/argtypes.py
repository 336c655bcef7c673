"""argparse ``type=`` converters for numeric options: a bad value is a usage error (exit 2,
argparse's message names the option) before the command does anything.

    p.add_argument("--steps", type=positive_int)
    p.add_argument("--passes", type=nonneg_int)
    p.add_argument("--max-size", type=int_range(16))
    p.add_argument("--size", type=size_wh(min_px=8, max_px=8192))

Each converter raises `argparse.ArgumentTypeError`, which argparse reports as
``argument --steps: must be an integer >= 1, got '0'``.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable
from pathlib import Path

__all__ = [
    "SEED_MAX", "fraction", "half_open_fraction", "int_range", "nonneg_float", "nonneg_int", "out_path",
    "positive_float", "positive_int", "seed", "size_wh"]

#: Seeds are in [0, SEED_MAX] (numpy's and torch's generators both accept this range).
SEED_MAX = 2**32 - 1


def _describe(lo: int | None, hi: int | None) -> str:
    if lo is not None and hi is not None:
        return f"an integer in [{lo}, {hi}]"
    if lo is not None:
        return f"an integer >= {lo}"
    return f"an integer <= {hi}"


def int_range(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """A converter accepting integers ``lo <= n <= hi`` (either bound may be None)."""

    def convert(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {_describe(lo, hi)}, got {text!r}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"must be {_describe(lo, hi)}, got {text!r}")
        return value

    convert.__name__ = f"int_range({lo}, {hi})"  # argparse shows the name in some messages
    return convert


def positive_int(text: str) -> int:
    """An integer >= 1."""
    return int_range(1)(text)


def nonneg_int(text: str) -> int:
    """An integer >= 0."""
    return int_range(0)(text)


def seed(text: str) -> int:
    """A seed: an integer in ``[0, SEED_MAX]``."""
    return int_range(0, SEED_MAX)(text)


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}")
    return value


def nonneg_float(text: str) -> float:
    """A finite number >= 0."""
    value = _float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}")
    return value


def fraction(text: str) -> float:
    """A number in ``[0, 1]``."""
    value = _float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a number in [0, 1], got {text!r}")
    return value


def half_open_fraction(text: str) -> float:
    """A number in ``[0, 1)``."""
    value = _float(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"must be a number in [0, 1), got {text!r}")
    return value


_SIZE_RE = re.compile(r"\s*(\d+)\s*[xX]\s*(\d+)\s*")


def size_wh(min_px: int = 1, max_px: int | None = None) -> Callable[[str], tuple[int, int]]:
    """A converter of ``WIDTHxHEIGHT`` (e.g. ``504x378``) to ``(W, H)``, each side in ``[min_px, max_px]``."""
    bound = f"{min_px}..{max_px}" if max_px is not None else f">= {min_px}"

    def convert(text: str) -> tuple[int, int]:
        m = _SIZE_RE.fullmatch(text)
        if m is None:
            raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 504x378, got {text!r}")
        w, h = int(m.group(1)), int(m.group(2))
        if min(w, h) < min_px or (max_px is not None and max(w, h) > max_px):
            raise argparse.ArgumentTypeError(f"each side must be {bound} px, got {text!r}")
        return w, h

    convert.__name__ = "size_wh"
    return convert


def out_path(text: str) -> Path:
    """An output path (``--out``): an empty or blank one is a usage error. `pathlib.Path("")` is the current
    folder, so without this ``--out ""`` (an unset shell variable) would write into the current folder."""
    if text.strip() == "":
        raise argparse.ArgumentTypeError("is empty: pass an output folder or file")
    return Path(text)
