"""One run per output folder at a time: `OUT/.denoise-gs.lock` holds the owner's pid."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from mvgeo.common.errors import InputError

__all__ = ["output_lock"]

LOCK_NAME = ".denoise-gs.lock"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def output_lock(out: Path) -> Iterator[None]:
    """Hold the lock of folder `out` (created if needed); a lock left by a dead process is taken over.

    Raises:
        InputError: a live process holds it.
    """
    out.mkdir(parents=True, exist_ok=True)
    lock = out / LOCK_NAME
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or "0")
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and _alive(pid):
                raise InputError(f"another run (pid {pid}) is writing this folder", path=out,
                                 fix="wait for it to finish, or use another --out") from None
            lock.unlink(missing_ok=True)
            continue
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        break
    else:
        raise InputError("cannot take the output lock", path=lock, fix="remove the lock file if no run is active")
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)
