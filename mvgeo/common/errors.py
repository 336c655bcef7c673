"""Typed errors shared by all packages.

`InputError` (and subclasses) are user-facing: the CLIs print them without a
traceback and exit with code 2. Their message names the offending file, key
or value and says how to fix it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path


class DgsError(Exception):
    """Base class of every error this project raises on purpose."""


class InputError(DgsError):
    """Bad user input: a missing/corrupt file, a wrong value, an unknown key.

    Args:
        message: what is wrong, in one sentence.
        path: the file or folder concerned, if any (shown first).
        fix: what the user should do about it.
    """

    def __init__(self, message: str, *, path: str | Path | None = None, fix: str | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        self.fix = fix
        super().__init__(self._format())

    def _format(self) -> str:
        text = f"{self.path}: {self.message}" if self.path is not None else self.message
        if self.fix:
            text += f"\n  fix: {self.fix}"
        return text


class ConfigError(InputError):
    """A configuration / scene file problem at a key path such as `cameras.rig.radius`.

    Args:
        message: what is wrong with the value.
        key: dotted key path inside the file.
        path: the file.
        expected: a description of what is accepted.
    """

    def __init__(
        self,
        message: str,
        *,
        key: str,
        path: str | Path | None = None,
        expected: str | None = None,
        fix: str | None = None,
    ):
        self.key = key
        self.expected = expected
        full = f"key '{key}': {message}"
        if expected:
            full += f" (expected {expected})"
        super().__init__(full, path=path, fix=fix)


class DisconnectedViewsError(InputError):
    """The images' pairs do not connect them all: the named views cannot be related to the others from
    these images alone (an input problem for the user, exit code 2; a failed geometry for a caller that can
    fall back on an earlier reconstruction)."""


class ShapeError(DgsError, ValueError):
    """An array/tensor argument has the wrong shape (a programming error)."""


class DegenerateGeometryError(DgsError):
    """The geometry admits no unique answer (e.g. zero baseline for triangulation,
    coincident points for Procrustes). Raised where a validity flag cannot carry it."""


def check_shape(x, expected: Sequence[str | int], name: str = "array") -> None:
    """Check `x.shape` against a pattern such as `["*", 3, 3]` or `["N", 2]`.

    `"*"` (first entry only) matches any number of leading batch dims; a string
    matches any size; an int must match exactly.

    Raises:
        ShapeError: naming the argument, the expected pattern and the actual shape.
    """
    shape = tuple(x.shape)
    pattern = list(expected)
    if pattern and pattern[0] == "*":
        pattern = pattern[1:]
        if len(shape) < len(pattern):
            raise ShapeError(f"{name}: expected shape (*, {', '.join(map(str, pattern))}), got {shape}")
        tail = shape[len(shape) - len(pattern):] if pattern else ()
    else:
        if len(shape) != len(pattern):
            raise ShapeError(f"{name}: expected shape ({', '.join(map(str, pattern))}), got {shape}")
        tail = shape
    for got, want in zip(tail, pattern, strict=True):
        if isinstance(want, int) and got != want:
            raise ShapeError(f"{name}: expected shape {tuple(expected)}, got {shape}")
