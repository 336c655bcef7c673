"""Progress bars for long loops (tqdm on stderr).

Disabled when `DGS_NO_PROGRESS=1` is set or stderr is not a terminal and
`DGS_PROGRESS=1` is not set, so logs in CI stay readable.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable, Iterator

from tqdm.auto import tqdm


def progress_enabled() -> bool:
    if os.environ.get("DGS_NO_PROGRESS") == "1":
        return False
    if os.environ.get("DGS_PROGRESS") == "1":
        return True
    return sys.stderr.isatty()


def progress[T](iterable: Iterable[T], *, desc: str, total: int | None = None, unit: str = "it") -> Iterator[T]:
    """Wrap `iterable` in a progress bar labelled `desc`."""
    return iter(tqdm(iterable, desc=desc, total=total, unit=unit, disable=not progress_enabled(), leave=False))


def progress_bar(*, desc: str, total: int, unit: str = "it") -> tqdm:
    """A manual progress bar (`bar.update(n)`, `bar.set_postfix(loss=...)`); close it or use `with`."""
    return tqdm(desc=desc, total=total, unit=unit, disable=not progress_enabled(), leave=False)
