"""Typed errors shared by all packages.

`InputError` (and subclasses) are user-facing: the CLIs print them without a
traceback and exit with code 2. Their message names the offending file, key
or value and says how to fix it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path


def _rebuilt(cls: type[DgsError], args: tuple, state: dict) -> DgsError:
    """`cls`'s error with `args` and attributes `state`, without calling its `__init__` (`DgsError.__reduce__`)."""
    err = cls.__new__(cls, *args)
    err.args = args
    err.__dict__.update(state)
    return err


class DgsError(Exception):
    """Base class of every error this project raises on purpose.

    Pickled as its arguments and attributes, not through `__init__`: an error whose constructor takes
    keyword-only arguments (`AlignmentRefusedError`'s `kind`, `UnposedViewsError`'s `views`) raised in a
    Ray task (`eval.distributed`) or another process reaches the caller as itself, with its attributes.
    """

    def __reduce__(self) -> tuple:
        return _rebuilt, (type(self), self.args, dict(self.__dict__))


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
    fall back on an earlier reconstruction).

    Args:
        views: the names of the views left out (the ones not in the largest connected group).
    """

    def __init__(self, message: str, *, views: Sequence[str] = (), path: str | Path | None = None,
                 fix: str | None = None):
        self.views = tuple(views)
        super().__init__(message, path=path, fix=fix)


class ShapeError(DgsError, ValueError):
    """An array/tensor argument has the wrong shape (a programming error)."""


class DegenerateGeometryError(DgsError):
    """The geometry admits no unique answer (e.g. zero baseline for triangulation,
    coincident points for Procrustes). Raised where a validity flag cannot carry it."""


class UnposedViewsError(DegenerateGeometryError):
    """A start or chaining step could not pose some views (no usable pair reaches them, or their pointmap
    gives no pose). Raised with view indices where the names are not known; `naming` gives the same error
    naming the views, for the caller that knows their names.

    Args:
        reason: what went wrong, without the views (e.g. "not connected to the others by any pair").
        views: the view indices concerned.
        names: their names, when known (the message lists them instead of the indices).
    """

    def __init__(self, reason: str, *, views: Sequence[int], names: Sequence[str] | None = None):
        self.reason, self.views, self.names = reason, tuple(int(v) for v in views), (
            None if names is None else tuple(names))
        shown = list(self.names) if self.names is not None else list(self.views)
        super().__init__(f"{'view' if len(shown) == 1 else 'views'} {shown}: {reason}")

    def naming(self, names: Sequence[str]) -> UnposedViewsError:
        """The same error with the views' names (`names[v]` for each index)."""
        return UnposedViewsError(self.reason, views=self.views, names=[names[v] for v in self.views])


class AlignmentRefusedError(DegenerateGeometryError):
    """The alignment's best solution is not supported by the evidence (`mvgeo.align.verdict`).

    Args:
        message: what is wrong and the likely causes.
        kind: the reason's kind (`mvgeo.align.verdict.REASON_KINDS`).
        views: the views concerned (empty when the reason concerns the whole reconstruction).
        fix: what the user can do (depends on the command: a caller may raise it again with its own).
    """

    def __init__(self, message: str, *, kind: str, views: Sequence[str] = (), fix: str | None = None):
        self.message, self.kind, self.views, self.fix = message, kind, tuple(views), fix
        super().__init__(message + (f"\n  fix: {fix}" if fix else ""))

    def with_fix(self, fix: str) -> AlignmentRefusedError:
        """The same refusal with another fix."""
        return AlignmentRefusedError(self.message, kind=self.kind, views=self.views, fix=fix)


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
