"""One run per output folder at a time: an `fcntl.flock` on `OUT/.denoise-gs.lock`.

The kernel holds the lock for as long as the owner keeps the file open and
drops it when the owner exits, however it exits; so a lock is never "stale"
and nothing has to guess from the file's content whether its owner is alive.
The file carries the owner's pid only for the error message.

The file is removed on release while the lock is still held. A process that
opened the old file just before sees, after taking the lock, that the path no
longer names the file it locked, and starts again on the new one.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import stat
from collections.abc import Iterator
from pathlib import Path

from mvgeo.common.errors import InputError
from mvgeo.common.output import LOCK_NAME, is_lock_content

__all__ = ["LOCK_NAME", "output_lock"]


def _owner_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _holds_a_pid_or_nothing(fd: int) -> bool:
    """The open lock file holds what this module writes there: nothing yet, or a pid (a user's file of that
    name holding anything else is not truncated)."""
    try:
        return is_lock_content(os.pread(fd, 33, 0))
    except OSError:
        return False


@contextlib.contextmanager
def output_lock(out: str | Path, *, wait: bool = False) -> Iterator[None]:
    """Hold the lock of folder `out` (created if needed) for the block's lifetime.

    Args:
        out: the folder.
        wait: where another process holds the lock, wait until it lets go instead of raising, however long
            that takes (`denoise-gs eval`'s ground-truth-pose variants, which read the runs they start
            from: they check the folder's stages under the lock one after the other). Never with a holder
            in this process: the lock is per open file, so a second `output_lock` of the same folder in
            one process would wait for itself.

    Raises:
        InputError: another process (or another holder in this process) has it, and `wait` is False.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lock = out / LOCK_NAME
    while True:
        try:  # never through a link of that name, nor into anything but a regular file: they are the user's
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NONBLOCK, 0o644)
        except OSError as exc:
            raise InputError(f"cannot open the lock file {LOCK_NAME} ({exc.strerror or exc})", path=lock,
                             fix="move it away if it is yours, or choose another --out; nothing was changed") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode) or not _holds_a_pid_or_nothing(fd):
            os.close(fd)
            raise InputError(f"{LOCK_NAME} in the output folder is not a lock file", path=lock,
                             fix="move it away if it is yours, or choose another --out; nothing was changed")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            pid = _owner_pid(fd)  # None while the owner has not written it yet: still a live owner
            os.close(fd)
            who = "another run" if pid is None else f"another run (pid {pid})"
            raise InputError(f"{who} is writing this folder", path=out,
                             fix="wait for it to finish, or use another --out") from None
        except BaseException:
            os.close(fd)
            raise
        try:
            same = os.path.samestat(os.stat(lock), os.fstat(fd))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the previous owner removed this file after we opened it: lock the new one
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        yield
    finally:
        try:
            lock.unlink(missing_ok=True)  # still holding the lock: nobody else can have replaced the file
        finally:
            os.close(fd)
