"""Atomic output folders and files: write into a temporary name, rename when complete.

A crash or an error never leaves a half-written folder under the final name,
and no temporary `.tmp-*` / `.old-*` entry stays behind on an error path.
What may be replaced is decided by the output policy (`mvgeo.common.output`).
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from pathlib import Path

from mvgeo.common.errors import InputError
from mvgeo.common.output import (
    LOCK_NAME,
    MANIFEST_NAME,
    OWNER_SUFFIX,
    OutputPlan,
    OwnerFile,
    make_dirs,
    recheck,
    remove_empty_dirs,
    remove_stale_leftovers,
    remove_tree,
    rename_no_replace,
    write_manifest,
)

__all__ = ["atomic_output_dir", "atomic_write_bytes", "atomic_write_text"]


def _commit_error(plan: OutputPlan, exc: OSError) -> InputError:
    what = f": {Path(exc.filename).name}" if isinstance(exc, FileExistsError) and exc.filename else ""
    return InputError(f"cannot put the output in place ({exc.strerror or exc}{what}); nothing was changed",
                      path=plan.out, fix="check what appeared at --out meanwhile, or choose another --out")


@contextlib.contextmanager
def atomic_output_dir(plan: OutputPlan) -> Iterator[Path]:
    """Yield an empty temporary folder; when the block completes it becomes `plan.path`.

    Args:
        plan: from `mvgeo.common.output.prepare_output` (made before the work). It is checked
            again here, since the folder may have changed while the output was computed.

    The manifest (`MANIFEST_NAME`) is added to the folder. What happens at `plan.path`:

    - ``"absent"``: the temporary folder is a hidden sibling, renamed to `plan.path`;
    - ``"empty"``: the temporary folder is inside `plan.path` and its entries are moved up (an
      empty folder, possibly the current directory, is never renamed);
    - ``"previous"`` (with `plan.overwrite`): the old output is renamed to a hidden sibling, the
      new one renamed in its place, then the old one removed; if the second rename fails the old
      output is put back.

    On an exception in the block the temporary folder (and any parent folder created for it) is
    removed and `plan.path` is untouched. The temporary folder and the renamed old output each have an
    owner file beside them while they exist (`mvgeo.common.output.OwnerFile`); what a killed command left
    is removed here first (`remove_stale_leftovers`: only folders whose owner's process is gone and whose
    owner file is not locked).

    Raises:
        InputError: `plan.path` is no longer acceptable (re-check), or the final renames fail.
    """
    if plan.resume:
        raise ValueError("atomic_output_dir replaces a folder; use resumable_output_dir for resume=True plans")
    plan = recheck(plan)
    tag = uuid.uuid4().hex[:8]
    if plan.state == "empty":
        created: list[Path] = []
        remove_stale_leftovers(plan.path)
        tmp = plan.path / f".tmp-{tag}"
    else:
        created = make_dirs(plan.path.parent)
        remove_stale_leftovers(plan.path.parent, plan.path.name)
        tmp = plan.path.parent / f".{plan.path.name}.tmp-{tag}"
    owner = None
    try:
        owner = OwnerFile(tmp)
        tmp.mkdir()
    except BaseException as exc:  # a Ctrl-C in between too: no owner file without its folder
        if owner is not None:
            owner.release()
        remove_empty_dirs(created)
        if isinstance(exc, OSError):
            raise InputError(f"cannot create the output folder ({exc.strerror or exc})", path=plan.out,
                             fix="choose an --out in a folder you can write to") from None
        raise
    try:
        yield tmp
        write_manifest(tmp, plan.command)
        _commit(plan, tmp, tag)
    except BaseException:
        remove_tree(tmp)
        owner.release()
        remove_empty_dirs(created)
        raise
    owner.release()


def _commit(plan: OutputPlan, tmp: Path, tag: str) -> None:
    path = plan.path
    if plan.state == "empty":  # `tmp` is inside; `_move_entries_up` checks that nothing else appeared
        _move_entries_up(plan, tmp)
        return
    now = recheck(plan)  # the folder must still be what the plan allows (raises InputError if not)
    if now.state != plan.state:
        raise InputError(f"--out changed while the output was computed (was {plan.state}, now {now.state})",
                         path=plan.out, fix="run the command again")
    if plan.state == "absent":
        try:
            os.rename(tmp, path)
        except OSError as exc:
            raise _commit_error(plan, exc) from None
    else:
        old = path.parent / f".{path.name}.old-{tag}"
        try:
            owner = OwnerFile(old)
        except OSError as exc:
            raise _commit_error(plan, exc) from None
        try:
            try:
                os.rename(path, old)
            except OSError as exc:
                raise _commit_error(plan, exc) from None
            try:
                os.rename(tmp, path)
            except OSError as exc:
                os.rename(old, path)
                raise _commit_error(plan, exc) from None
            remove_tree(old)
        finally:
            owner.release()


def _move_entries_up(plan: OutputPlan, tmp: Path) -> None:
    path = plan.path
    others = set(os.listdir(path)) - {tmp.name, tmp.name + OWNER_SUFFIX, LOCK_NAME}
    if others:
        raise InputError(f"--out is no longer empty ({sorted(others)[:3]} appeared while computing)",
                         path=plan.out, fix="choose another --out, or run the command again")
    moved: list[Path] = []
    # The manifest last: it is what marks a finished output, so a command killed part-way through the moves
    # leaves a folder that no later command takes for one (it holds some results and no manifest).
    names = sorted(os.listdir(tmp), key=lambda n: (n == MANIFEST_NAME, n))
    try:
        for name in names:
            dst = path / name
            rename_no_replace(tmp / name, dst)  # never over an entry that appeared since the check above
            moved.append(dst)
        tmp.rmdir()
    except BaseException as exc:  # a Ctrl-C between two moves too: only what was just moved in is taken out
        for dst in moved:  # the folder was empty before
            if dst.is_dir() and not dst.is_symlink():
                remove_tree(dst)
            else:
                dst.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _commit_error(plan, exc) from None
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write a file atomically (temporary sibling + rename); the temporary file never stays behind."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write a text file atomically (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))
