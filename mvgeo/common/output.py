"""One output policy for every command that writes an `--out` folder.

A command never destroys data it did not write. `prepare_output` decides, before
any computation, what may happen at `--out`:

- nothing there, or an empty folder: the output is written there;
- a folder holding a previous output of the same command, recognised by the
  manifest `OUT/.denoise-gs-output.json` that every command writes (command
  name, package version, creation time and, for the commands that write their
  folder at once, every file and folder they wrote with its size, modification
  time and SHA-256): replaced with `overwrite=True` (`--overwrite`) only while it
  holds nothing but those files, unchanged; or, for the commands that resume
  inside their folder (`resume=True`: `denoise-gs run`, `eval`, `cost`, whose
  stages record their own files), reused;
- anything else (a non-empty folder without our manifest, a previous output
  holding files the command did not write or changed since, a file, a broken
  symbolic link, an output of another command) is refused with `InputError`
  naming the path and the fix.

A single output file (`prepare_output_file`) is replaced with `overwrite=True`
only when the hidden record beside it (`write_file_record`) says this command
wrote it and its content is unchanged. `write_output_file` checks again after
the work: a new file is hard-linked into place (which fails if one appeared
meanwhile), an existing one is re-checked just before the rename.

It also refuses an `--out` that is, contains or lies inside an input (symbolic
links and `..` resolved), and one whose nearest existing parent cannot be
written (checked with `os.access` and a real probe folder, so a read-only
parent fails at once, not after the computation). An existing folder that is
the current directory is written into only when empty (it is never renamed);
replacing a previous output there is refused (run from another folder).

`mvgeo.common.atomic.atomic_output_dir(plan)` then writes the folder
atomically and `resumable_output_dir(plan)` opens a resumable one. The
temporary folder it writes into and a replaced output while it is renamed
aside each have an owner file beside them naming the process (host and pid);
a pair whose process is gone (a command killed by SIGKILL or out of memory)
is removed by the next command writing there. Nothing else with a similar name
is ever removed.
This module imports only the standard library.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import json
import logging
import os
import re
import shutil
import socket
import stat
import tempfile
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from mvgeo.common.digest import file_sha256
from mvgeo.common.errors import InputError

_log = logging.getLogger(__name__)

__all__ = [
    "LOCK_NAME",
    "MANIFEST_NAME",
    "OUT_HELP",
    "OUT_RESUME_HELP",
    "OVERWRITE_HELP",
    "OWNER_SUFFIX",
    "OutputPlan",
    "OwnerFile",
    "as_output_plan",
    "prepare_output",
    "file_record_path",
    "foreign_entries",
    "is_lock_content",
    "prepare_output_file",
    "read_manifest",
    "remove_stale_leftovers",
    "rename_no_replace",
    "restore_retired_output",
    "resumable_output_dir",
    "stale_leftovers",
    "write_file_record",
    "write_manifest",
    "write_output_file",
]

#: The manifest every command writes at the top of its output folder.
MANIFEST_NAME = ".denoise-gs-output.json"
#: The lock file of a resumable output folder (`eval.pipeline.lock`); a folder holding only this
#: file (left by a run that was killed) counts as empty.
LOCK_NAME = ".denoise-gs.lock"
MANIFEST_FORMAT = 1
#: The longest file name (bytes) the common file systems take.
_NAME_MAX = 255
#: Temporary entries `mvgeo.common.atomic` creates inside an empty `--out` (removed unless the process
#: is killed).
_TEMP_NAME = re.compile(r"\.tmp-[0-9a-f]{8}")

#: The temporary and retired folders `mvgeo.common.atomic` makes: `.tmp-TAG` inside an empty `--out`,
#: `.<name>.tmp-TAG` and `.<name>.old-TAG` beside it. Each has an owner file, the name plus `OWNER_SUFFIX`.
_LEFTOVER_NAME = re.compile(r"\.(?:(?P<out>.+)\.)?(?P<kind>tmp|old)-[0-9a-f]{8}")
OWNER_SUFFIX = ".owner"

#: `--out` / `--overwrite` help texts of the commands that replace their output folder.
OUT_HELP = ("output folder: a new or empty one (written there; `.` works only when the current folder is "
            "empty), or a previous output of this command with --overwrite; anything else is refused")
OVERWRITE_HELP = "replace --out when it holds a previous output of this same command (nothing else is ever replaced)"
#: `--out` help text of the commands that resume inside their output folder.
OUT_RESUME_HELP = ("output folder (resumable): a new or empty one, or a previous output of this command, which is "
                   "resumed; a folder holding anything else is refused")

OutputState = Literal["absent", "empty", "previous"]


@dataclass(frozen=True)
class OutputPlan:
    """What `prepare_output` found at `--out` and what may be done there.

    Attributes:
        out: the path as the user gave it (used in messages).
        path: absolute path with symbolic links and `..` resolved: where the files go.
        command: the command writing it, e.g. ``"mvgeo align"``.
        state: ``"absent"`` (nothing there), ``"empty"`` (an empty folder) or ``"previous"``
            (a previous output of `command`, to replace or resume).
        overwrite: a previous output may be replaced.
        resume: the command resumes inside the folder instead of replacing it.
        inputs: the resolved input paths (checked again when the output is committed).
    """

    out: Path
    path: Path
    command: str
    state: OutputState
    overwrite: bool = False
    resume: bool = False
    inputs: tuple[Path, ...] = ()


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("denoise-gs")
    except Exception:  # not installed (running from a checkout)
        return "0+unknown"


def _file_entry(path: Path) -> dict[str, object]:
    st = path.lstat()
    if stat.S_ISLNK(st.st_mode):
        return {"link": os.readlink(path)}
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": file_sha256(path)}


def _same_file(path: Path, entry: object) -> bool:
    """`path` is still the file `entry` (`_file_entry`) describes: the same link target, or a regular file
    of the same size and SHA-256 (the modification time is not trusted: it can be set back)."""
    if not isinstance(entry, dict):
        return False
    st = path.lstat()
    if "link" in entry:
        return stat.S_ISLNK(st.st_mode) and os.readlink(path) == entry["link"]
    if not stat.S_ISREG(st.st_mode) or st.st_size != entry.get("size"):
        return False
    return file_sha256(path) == entry.get("sha256")


def _tree(folder: Path) -> tuple[list[str], list[str]]:
    """(folders, files and links) under `folder`, relative POSIX paths, the top-level manifest left out."""
    dirs, files = [], []
    for root, subdirs, names in os.walk(folder):
        rel_root = Path(root).relative_to(folder)
        for d in list(subdirs):
            if os.path.islink(os.path.join(root, d)):  # a link to a folder is an entry, not walked
                subdirs.remove(d)
                names.append(d)
            else:
                dirs.append((rel_root / d).as_posix())
        for n in names:
            rel = (rel_root / n).as_posix()
            if rel != MANIFEST_NAME:
                files.append(rel)
    return sorted(dirs), sorted(files)


def _write_json(path: Path, data: dict) -> None:
    """`path` written as indented JSON through a temporary sibling (`NAME.tmp-PID`) and a rename."""
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_manifest(folder: str | Path, command: str, *, record_files: bool = True) -> Path:
    """Write `folder/.denoise-gs-output.json`: ``{"command", "version", "created_utc", "format"}`` and,
    with `record_files`, ``"dirs"`` (every folder under `folder`) and ``"files"`` (every file or link:
    size, modification time and SHA-256, or the link's target), what `--overwrite` may replace later
    (compared by size and SHA-256).
    The resumable commands write it without files when they open their folder (their stages record
    what they write)."""
    folder = Path(folder)
    path = folder / MANIFEST_NAME
    data: dict[str, object] = {"command": command, "version": _version(),
                               "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                               "format": MANIFEST_FORMAT}
    if record_files:
        dirs, files = _tree(folder)
        data["dirs"] = dirs
        data["files"] = {rel: _file_entry(folder / rel) for rel in files}
    _write_json(path, data)
    return path


def foreign_entries(folder: str | Path, manifest: dict) -> list[str] | None:
    """What under `folder` its manifest does not account for: files and folders it does not list and
    listed files that changed (relative paths, sorted); None when the manifest lists no files."""
    files, dirs = manifest.get("files"), manifest.get("dirs")
    if not isinstance(files, dict) or not isinstance(dirs, list):
        return None
    folder = Path(folder)
    found_dirs, found_files = _tree(folder)
    known_dirs = set(dirs)
    out = [d + "/" for d in found_dirs if d not in known_dirs]
    out += [f for f in found_files if f not in files or not _same_file(folder / f, files[f])]
    return sorted(out)


def read_manifest(folder: str | Path) -> dict | None:
    """The manifest of `folder`, or None when it has none or it cannot be parsed."""
    path = Path(folder) / MANIFEST_NAME
    if not path.is_file():  # e.g. a FIFO of that name, whose read would block
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):  # RecursionError: deeply nested JSON
        return None
    return data if isinstance(data, dict) and isinstance(data.get("command"), str) else None


def _resolve(p: str | Path) -> Path:
    return Path(os.path.abspath(os.fspath(p))).resolve()


def _relation(out: Path, inp: Path) -> str | None:
    if out == inp:
        return "is"
    if out in inp.parents:
        return "contains"
    if inp in out.parents:
        return "is inside"
    return None


def _check_inputs(plan_out: Path, path: Path, inputs: Iterable[str | Path | None]) -> tuple[Path, ...]:
    resolved = []
    for inp in inputs:
        if inp is None or os.fspath(inp) == "":
            continue
        ip = _resolve(inp)
        resolved.append(ip)
        rel = _relation(path, ip)
        if rel is not None:
            what = {"is": "is the input", "contains": "contains the input", "is inside": "is inside the input"}[rel]
            raise InputError(f"--out {what} '{inp}'", path=plan_out,
                             fix="write the output to a separate folder, outside every input")
    return tuple(resolved)


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p):
        if p.parent == p:
            break
        p = p.parent
    return p


def _check_writable(folder: Path, plan_out: Path) -> None:
    """`folder` (an existing path) must be a folder we can create entries in."""
    if not folder.is_dir():
        raise InputError(f"cannot create the output: {folder} is not a folder", path=plan_out,
                         fix="choose an --out whose parent is a folder")
    problem = None
    if not os.access(folder, os.W_OK | os.X_OK):
        problem = "permission denied"
    else:
        try:
            probe = tempfile.mkdtemp(prefix=".denoise-gs-probe-", dir=folder)
        except OSError as exc:
            problem = exc.strerror or str(exc)
        else:
            os.rmdir(probe)
    if problem is not None:
        raise InputError(f"cannot write the output: {folder} is not writable ({problem})", path=plan_out,
                         fix="choose an --out in a folder you can write to")


def is_lock_content(data: bytes) -> bool:
    """`data` (the first 33 bytes of a file, or more) is what `eval.pipeline.lock.output_lock` writes in its
    lock file: nothing yet, or a pid; anything else is a user's file that happens to carry the name."""
    text = data.decode("ascii", errors="replace").strip()
    return len(data) <= 32 and (text == "" or text.isdigit())


def _is_lock_file(path: Path) -> bool:
    """`path` is a regular file holding what `eval.pipeline.lock.output_lock` writes (`is_lock_content`)."""
    try:
        if not stat.S_ISREG(path.lstat().st_mode):
            return False
        with open(path, "rb") as fh:
            return is_lock_content(fh.read(33))
    except OSError:
        return False


class OwnerFile:
    """The owner file of a temporary or retired folder `entry` (`entry` + `OWNER_SUFFIX`): JSON naming this
    process (host, pid), created before `entry` is created or renamed into place and locked (`flock`) by
    this process until `release` (which removes it). `stale_leftovers` takes a folder for a dead command's
    only when the process is gone and the lock is free, so a live command is recognised even from another
    pid namespace (a container) sharing the folder.

    Raises:
        OSError: the file cannot be created (it exists, the folder is not writable).
    """

    def __init__(self, entry: Path):
        self.path = entry.with_name(entry.name + OWNER_SUFFIX)
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        try:
            with contextlib.suppress(OSError):  # a file system without flock: the pid alone tells
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            info = {"entry": entry.name, "host": socket.gethostname(), "pid": os.getpid()}
            os.write(fd, (json.dumps(info) + "\n").encode())
        except BaseException:
            os.close(fd)
            self.path.unlink(missing_ok=True)
            raise
        self._fd: int | None = fd

    def release(self) -> None:
        """Remove the owner file, then drop its lock (idempotent)."""
        if self._fd is None:
            return
        self.path.unlink(missing_ok=True)
        os.close(self._fd)
        self._fd = None


def _owner_locked(owner: Path) -> bool:
    """A live `OwnerFile` holds `owner`'s lock (True also when the file cannot be opened: then nothing is
    known); False when the lock is free or the file system has no `flock`."""
    try:
        fd = os.open(owner, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)  # shared: conflicts with the owner's, needs no write access
        return False
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def _process_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # e.g. another user's process
        return False
    return False


def stale_leftovers(folder: Path, out_name: str | None = None) -> list[Path]:
    """The temporary and retired folders (and single output files' temporary files) in `folder` that a killed
    command left, with their owner files
    (with `out_name`: only those of the output `folder/out_name`, `.<out_name>.tmp-TAG` and
    `.<out_name>.old-TAG`; else any, e.g. `.tmp-TAG` in an empty `--out`): a folder is one only with an
    owner file an `OwnerFile` wrote for it on this host whose process is gone and whose lock is free. An
    owner file whose folder was never created (the process died in between) counts alone. Never raises.

    A retired folder `.<name>.old-TAG` whose output `<name>` is missing is not one: the command was killed
    between its two renames, and that folder is the only copy of the previous output (left for the user).
    """
    found: list[Path] = []
    try:
        names = set(os.listdir(folder))
    except OSError:
        return found
    for name in sorted(names):
        entry_name = name.removesuffix(OWNER_SUFFIX)
        m = _LEFTOVER_NAME.fullmatch(entry_name)
        if m is None or (out_name is not None and m["out"] != out_name):
            continue
        entry, owner = folder / entry_name, folder / (entry_name + OWNER_SUFFIX)
        alone = entry_name not in names
        if name == entry_name and alone:  # a folder-like name without its owner file: not ours to judge
            continue
        if name != entry_name and not alone:  # the owner file of a folder: judged with the folder
            continue
        try:
            # A folder, or the temporary file of a single output file (`write_output_file`).
            if not alone and (entry.is_symlink() or not (entry.is_dir() or (m["kind"] == "tmp" and entry.is_file()))):
                continue
            if not alone and m["kind"] == "old" and not os.path.lexists(folder / (m["out"] or "")):
                continue  # the only copy of a previous output (see above)
        except OSError:
            continue
        if _owner_gone(owner, entry_name):
            found += [owner] if alone else [entry, owner]
    return found


def _owner_gone(owner: Path, entry_name: str) -> bool:
    """`owner` is an owner file an `OwnerFile` wrote for `entry_name` on this host, its process is gone and
    its lock is free. Never raises."""
    try:
        st = owner.lstat()  # a regular file: a FIFO would block the read, a link may point anywhere
        if not stat.S_ISREG(st.st_mode) or st.st_size > 4096:
            return False
        info = json.loads(owner.read_text())
        pid = info.get("pid") if isinstance(info, dict) else None
        return (isinstance(info, dict) and info.get("entry") == entry_name
                and info.get("host") == socket.gethostname()
                and type(pid) is int and 0 < pid < 2**31 and pid != os.getpid() and _process_gone(pid)
                and not _owner_locked(owner))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):  # RecursionError: deeply nested JSON
        return False


@functools.cache
def _renameat2():
    """libc's `renameat2`, or None where the C library has none (not Linux, or glibc before 2.28)."""
    import ctypes
    import ctypes.util

    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True).renameat2
    except (OSError, AttributeError):
        return None


def rename_no_replace(src: Path, dst: Path, *, fallback: bool = True) -> None:
    """Rename `src` to `dst` only if nothing is at `dst`: a plain rename silently replaces a file, or an empty
    folder, that appeared at `dst` after a check. Linux `renameat2(RENAME_NOREPLACE)` makes the check and the
    rename one step; where it is missing (or the file system refuses the flag) `fallback` checks, then renames
    (a gap of microseconds), and without `fallback` nothing is moved (`OSError`).

    Raises:
        FileExistsError: something is at `dst` (nothing was moved).
        OSError: the rename failed otherwise.
    """
    import ctypes

    fn = _renameat2()
    if fn is not None:
        at_fdcwd, rename_noreplace = -100, 1
        if fn(at_fdcwd, os.fsencode(src), at_fdcwd, os.fsencode(dst), rename_noreplace) == 0:
            return
        err = ctypes.get_errno()
        if err == errno.EEXIST:
            raise FileExistsError(err, os.strerror(err), str(dst))
        if err not in (errno.EINVAL, errno.ENOSYS):  # EINVAL / ENOSYS: the flag or the call is unsupported
            raise OSError(err, os.strerror(err), str(dst))
    if not fallback:
        raise OSError(errno.ENOSYS, "no rename that refuses to replace", str(dst))
    if os.path.lexists(dst):
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(dst))
    os.rename(src, dst)


def restore_retired_output(path: Path) -> Path | None:
    """Put back the previous output of `path` that a killed `--overwrite` left retired.

    Replacing an output renames it to `.<name>.old-TAG` beside it, then the new one into place; a command
    killed between the two renames leaves no `<name>`, and the retired folder is the only copy of the previous
    output. When `path` is missing and exactly one such folder has an owner file whose process is gone (and
    whose lock is free), it is renamed back to `path` and its owner file removed, so the next command finds
    the previous output where the user left it (and resumes in it, or replaces it only with --overwrite).
    Returns the folder it restored from, or None. Never raises.
    """
    try:
        if os.path.lexists(path):
            return None
        names = set(os.listdir(path.parent))
    except OSError:
        return None
    retired = []
    for name in sorted(names):
        m = _LEFTOVER_NAME.fullmatch(name)
        if m is None or m["kind"] != "old" or m["out"] != path.name or name + OWNER_SUFFIX not in names:
            continue
        entry = path.parent / name
        if not entry.is_symlink() and entry.is_dir() and _owner_gone(path.parent / (name + OWNER_SUFFIX), name):
            retired.append(entry)
    if len(retired) != 1:
        return None
    try:
        rename_no_replace(retired[0], path, fallback=False)
    except OSError:
        return None
    retired[0].with_name(retired[0].name + OWNER_SUFFIX).unlink(missing_ok=True)
    _log.warning("restored the previous output %s from %s, where a command killed while replacing it had left it",
                 path, retired[0].name)
    return retired[0]


def remove_stale_leftovers(folder: Path, out_name: str | None = None) -> None:
    """Remove what `stale_leftovers(folder, out_name)` finds."""
    for path in stale_leftovers(folder, out_name):
        if path.is_dir():
            remove_tree(path)
        else:
            path.unlink(missing_ok=True)


def _entries(folder: Path, *, resume: bool) -> list[str]:
    names = os.listdir(folder)
    stale = {p.name for p in stale_leftovers(folder)}
    return [n for n in names if n not in stale and not (resume and n == LOCK_NAME and _is_lock_file(folder / n))]


def _is_cwd_or_ancestor(path: Path) -> bool:
    try:
        cwd = _resolve(os.getcwd())
    except OSError:
        return False
    return path == cwd or path in cwd.parents


#: Bytes `mvgeo.common.atomic` adds to `--out`'s name for the folders it keeps beside it while it writes:
#: `.<name>.tmp-TAG` / `.<name>.old-TAG` (TAG: 8 hex digits) and their owner files (`OWNER_SUFFIX`).
_SIBLING_EXTRA = len(".") + len(".tmp-") + 8 + len(OWNER_SUFFIX)


def _check_name_length(out: Path, path: Path) -> None:
    """Refuse an `--out` whose name leaves no room for the folders written beside it (`_SIBLING_EXTRA`): the
    file system would refuse them only when the output is written, after the work."""
    longest = _NAME_MAX - _SIBLING_EXTRA
    n = len(os.fsencode(path.name))
    if n > longest:
        raise InputError(f"--out's folder name is too long ({n} bytes; at most {longest}, to leave room for the "
                         "temporary folder written beside it)", path=out, fix="choose a shorter --out name")


def prepare_output(out: str | Path, *, command: str, inputs: Iterable[str | Path | None] = (),
                   overwrite: bool = False, resume: bool = False) -> OutputPlan:
    """Check `out` against the output policy (module docstring) before any work; create nothing, with one
    exception: a previous output that a killed `--overwrite` left retired beside a missing `out` is renamed
    back first (`restore_retired_output`).

    Args:
        out: the `--out` folder.
        command: the command's name as the user types it, e.g. ``"splat render"``.
        inputs: every input file or folder of the command (None entries are skipped).
        overwrite: a previous output of `command` at `out` may be replaced (`--overwrite`).
        resume: the command resumes inside `out` (a previous output is reused, never replaced).

    Returns:
        The plan for `atomic_output_dir` / `resumable_output_dir`.

    Raises:
        InputError: `out` is refused; the message names the path and the fix.
    """
    if os.fspath(out).strip() == "":
        raise InputError("--out is empty", fix="pass an output folder")
    out = Path(out)
    if out.is_symlink() and not out.exists():  # the link's target may be an output a killed --overwrite retired
        restore_retired_output(_resolve(out))
    if out.is_symlink() and not out.exists():
        raise InputError("--out is a broken symbolic link", path=out,
                         fix="remove the link or choose another --out")
    path = _resolve(out)
    resolved_inputs = _check_inputs(out, path, inputs)
    restore_retired_output(path)  # a killed --overwrite's only copy of the previous output, put back first
    state: OutputState
    if os.path.lexists(path) and not path.is_dir():
        raise InputError("--out exists and is not a folder", path=out,
                         fix="choose another --out (a new or empty folder), or remove the file yourself")
    if not path.is_dir():
        state = "absent"
        _check_writable(_nearest_existing(path.parent), out)
    else:
        try:
            entries = _entries(path, resume=resume)
        except OSError as exc:
            raise InputError(f"cannot read the output folder ({exc.strerror or exc})", path=out,
                             fix="choose another --out") from None
        manifest = read_manifest(path)
        if not entries:
            state = "empty"
        elif manifest is not None and manifest["command"] == command:
            state = "previous"
        elif manifest is not None:
            raise InputError(f"--out holds the output of `{manifest['command']}`, not of `{command}`", path=out,
                             fix="choose another --out (a new or empty folder)")
        else:
            shown = ", ".join(repr(n) for n in sorted(entries)[:3]) + (", ..." if len(entries) > 3 else "")
            if all(_TEMP_NAME.fullmatch(n.removesuffix(OWNER_SUFFIX)) for n in entries):
                raise InputError(f"--out holds only the temporary folder of an interrupted run ({shown})", path=out,
                                 fix="delete it yourself if no command is writing to --out now, or choose another "
                                     "--out; nothing was changed")
            if stale_leftovers(path):  # `entries` leaves them out
                raise InputError(f"--out holds an unfinished output ({shown}) beside the temporary folder of a "
                                 "command killed while it moved its results in", path=out,
                                 fix="if those are that command's, delete the folder and run it again; else choose "
                                     "a new or empty folder for --out; nothing was changed")
            raise InputError(f"--out is a folder that holds files `{command}` did not write ({shown})", path=out,
                             fix="choose a new or empty folder for --out; nothing was changed")
        if state == "previous" and not resume:
            if not overwrite:
                raise InputError(f"--out holds a previous output of `{command}`", path=out,
                                 fix="pass --overwrite (overwrite=True in Python) to replace it, or choose "
                                     "another --out")
            if _is_cwd_or_ancestor(path):
                raise InputError("--out is the current folder (or holds it); a previous output there cannot be "
                                 "replaced while it is in use", path=out,
                                 fix="run the command from another folder (e.g. `cd ..`), or choose another --out")
            foreign = foreign_entries(path, manifest)
            if foreign is None:
                raise InputError(f"--out holds an output of `{command}` whose manifest does not list its files "
                                 "(written by an older version), so what else it holds cannot be told", path=out,
                                 fix="check the folder and delete it yourself, or choose another --out; nothing "
                                     "was changed")
            if foreign:
                shown = ", ".join(repr(n) for n in foreign[:3]) + (", ..." if len(foreign) > 3 else "")
                raise InputError(f"--out holds a previous output of `{command}` and {len(foreign)} entr"
                                 f"{'y' if len(foreign) == 1 else 'ies'} it did not write or that changed since "
                                 f"({shown})", path=out,
                                 fix="move them out of --out, or choose another --out; nothing was changed")
        # Replacing renames `path` inside its parent; writing into an empty or resumed folder creates
        # entries inside `path` itself.
        _check_writable(path.parent if state == "previous" and not resume else path, out)
    if not resume and state != "empty":  # the output is written beside `path`, then renamed into place
        _check_name_length(out, path)
    return OutputPlan(out=out, path=path, command=command, state=state, overwrite=overwrite, resume=resume,
                      inputs=resolved_inputs)


def as_output_plan(out: OutputPlan | str | Path, *, command: str, overwrite: bool = False) -> OutputPlan:
    """`out` itself when it is a plan for `command`, else `prepare_output(out, command=..., overwrite=...)`.

    The library writers (`write_align_result`, `write_dataset`, ...) accept either: a plan made by
    their command line up front, or a path, checked here (by default an existing output is refused).
    """
    if isinstance(out, OutputPlan):
        if out.command != command:
            raise ValueError(f"output plan of {out.command!r} passed to a writer of {command!r}")
        return out
    return prepare_output(out, command=command, overwrite=overwrite)


def recheck(plan: OutputPlan) -> OutputPlan:
    """The plan made again just before writing: what is at `--out` may have changed during the work."""
    return prepare_output(plan.out, command=plan.command, inputs=plan.inputs, overwrite=plan.overwrite,
                          resume=plan.resume)


def make_dirs(path: Path) -> list[Path]:
    """`mkdir -p path`; return the folders created, deepest last."""
    missing = []
    p = path
    while not os.path.lexists(p):
        missing.append(p)
        p = p.parent
    created = []
    for d in reversed(missing):
        try:
            d.mkdir()
        except FileExistsError:
            continue
        created.append(d)
    return created


def remove_empty_dirs(created: list[Path]) -> None:
    """Remove the folders of `make_dirs` that are still empty, deepest first."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:
            break


@contextlib.contextmanager
def resumable_output_dir(plan: OutputPlan) -> Iterator[Path]:
    """Open the resumable output folder of `plan` (created if needed, manifest written) and yield it.

    When the block raises and the folder holds nothing but what this call added (the manifest, a
    lock file), that is removed again: a failed first run leaves no empty `--out` behind.
    """
    if not plan.resume:
        raise ValueError("resumable_output_dir needs a plan made with resume=True")
    plan = recheck(plan)
    created = make_dirs(plan.path)
    remove_stale_leftovers(plan.path)  # what a killed command left inside (`stale_leftovers`)
    wrote_manifest = False
    try:
        if read_manifest(plan.path) is None:
            write_manifest(plan.path, plan.command, record_files=False)
            wrote_manifest = True
    except OSError as exc:
        remove_empty_dirs(created)
        raise InputError(f"cannot write the output folder ({exc.strerror or exc})", path=plan.out,
                         fix="choose an --out in a folder you can write to") from None
    try:
        yield plan.path
    except BaseException:
        if wrote_manifest:
            with contextlib.suppress(OSError):
                # Only the manifest: with a lock file there another run holds the folder and relies on it.
                if set(os.listdir(plan.path)) == {MANIFEST_NAME}:
                    (plan.path / MANIFEST_NAME).unlink(missing_ok=True)
                    remove_empty_dirs(created)
        raise


def file_record_path(path: str | Path) -> Path:
    """The hidden record beside an output file: ``DIR/.NAME.denoise-gs-output.json``."""
    path = Path(path)
    return path.with_name(f".{path.name}{MANIFEST_NAME}")


def write_file_record(path: str | Path, command: str) -> Path:
    """Record that `command` wrote the file `path` (its size, modification time and SHA-256) in
    `file_record_path(path)`, so that a later ``--overwrite`` may replace it while it is unchanged."""
    path = Path(path)
    record = file_record_path(path)
    data = {"command": command, "version": _version(),
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "format": MANIFEST_FORMAT,
            "file": path.name, **_file_entry(path)}
    _write_json(record, data)
    return record


def _read_file_record(path: Path) -> dict | None:
    """The record `write_file_record` wrote beside `path`: a regular file (not a link) holding a JSON object
    with a `command` and `path`'s name as `file`; None when there is no such record."""
    record = file_record_path(path)
    try:
        if not stat.S_ISREG(record.lstat().st_mode):
            return None
        data = json.loads(record.read_text())
    except (OSError, ValueError, RecursionError):  # RecursionError: deeply nested JSON
        return None
    if not isinstance(data, dict) or not isinstance(data.get("command"), str) or data.get("file") != path.name:
        return None
    return data


def _written_by(path: Path, command: str) -> str | None:
    """None when `file_record_path(path)` says `command` wrote `path` and it is unchanged, else why not."""
    data = _read_file_record(path)
    if data is None:
        return f"it has no record of being written by `{command}`"
    if not isinstance(data, dict) or data.get("command") != command or data.get("file") != path.name:
        return f"its record does not say `{command}` wrote it"
    try:
        same = _same_file(path, data)
    except OSError:
        same = False
    return None if same else f"it changed since `{command}` wrote it"


def prepare_output_file(out: str | Path, *, command: str, inputs: Iterable[str | Path | None] = (),
                        overwrite: bool = False, example_name: str = "out.json") -> Path:
    """The policy for a single output file (e.g. `denoise select --out FILE`); return its resolved path.

    A folder at `out` is refused; an existing file is replaced only with `overwrite` and only when
    `command` wrote it (`write_file_record`; `write_output_file` writes both and checks again) and it has not
    changed since; the file must not be an input or lie inside one; its nearest existing parent must
    be writable. Creates nothing. `example_name`: the file name the message suggests when `out` is a folder.

    Raises:
        InputError: naming the path and the fix.
    """
    if os.fspath(out).strip() == "":
        raise InputError("--out is empty", fix="pass an output file")
    out = Path(out)
    if out.is_symlink() and not out.exists():
        raise InputError("--out is a broken symbolic link", path=out, fix="remove the link or choose another --out")
    path = _resolve(out)
    _check_inputs(out, path, inputs)
    if path.is_dir():
        raise InputError("--out is a folder; it must name a file", path=out,
                         fix=f"pass a file name, e.g. --out {out / example_name}")
    if len(os.fsencode(file_record_path(path).name)) > _NAME_MAX:
        raise InputError(f"--out's file name is too long to keep the record beside it ({len(path.name)} "
                         f"characters; at most {_NAME_MAX - len(MANIFEST_NAME) - 1} bytes)", path=out,
                         fix="choose a shorter file name")
    record = file_record_path(path)
    if os.path.lexists(record) and _read_file_record(path) is None:
        raise InputError(f"{record.name} beside --out is not a record this toolkit wrote, and writing --out would "
                         "replace it", path=record,
                         fix="move it away yourself, or choose another --out; nothing was changed")
    if os.path.lexists(path):
        if not overwrite:
            raise InputError("--out already exists", path=out,
                             fix="pass --overwrite to replace it if this command wrote it, or choose another --out")
        why = _written_by(path, command)
        if why is not None:
            raise InputError(f"--out already exists and {why}; only a file this command wrote is replaced",
                             path=out, fix="choose another --out (or move the file away yourself); nothing was "
                                           "changed")
        _check_writable(path.parent, out)
    else:
        _check_writable(_nearest_existing(path.parent), out)
    return path


def write_output_file(path: Path, command: str, write: Callable[[Path], object]) -> Path:
    """Write the single output file `path` (planned by `prepare_output_file`) and its record.

    `write(tmp)` writes the content to a temporary sibling; it is then published without ever replacing
    what `command` did not write: where nothing is at `path` the file is hard-linked into place, which fails
    if a file appeared there since the plan (an atomic no-replace); where something is there it is checked
    again (`command` wrote it and it is unchanged) just before the rename. Then the record
    (`write_file_record`). The temporary file is removed unless the process is killed; it has an owner file
    (`OwnerFile`), so the next call for `path` removes what a killed one left (`remove_stale_leftovers`).

    Raises:
        InputError: `path` was created, or changed, by someone else while the content was being made
            (nothing was replaced).
    """
    path = Path(path)
    created: list[Path] = []
    tmp = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        created = make_dirs(path.parent)  # `prepare_output_file` accepts a folder still to be made
        remove_stale_leftovers(path.parent, path.name)  # a killed call's temporary file, with its dead owner
        owner = OwnerFile(tmp)
    except OSError as exc:
        remove_empty_dirs(created)
        raise InputError(f"cannot write beside the output file ({exc.strerror or exc})", path=path.parent,
                         fix="choose another --out (a folder you can write)") from None

    def changed(why: str) -> InputError:
        return InputError(f"--out changed while the output was being made: {why}; only a file this command "
                          "wrote is replaced", path=path,
                          fix="choose another --out (or move the file away yourself); nothing was replaced")

    done = False
    try:
        write(tmp)
        if not os.path.lexists(path):
            try:
                os.link(tmp, path)  # fails when `path` exists: never replaces
            except FileExistsError:
                raise changed("a file appeared there") from None
            except OSError:  # a file system without hard links: claim the name, then rename over the claim
                try:
                    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644))
                except FileExistsError:
                    raise changed("a file appeared there") from None
                try:
                    os.replace(tmp, path)
                except OSError:
                    path.unlink(missing_ok=True)  # our empty claim
                    raise
        else:
            why = _written_by(path, command)
            if why is not None:
                raise changed(why)
            os.replace(tmp, path)
        done = True
    finally:
        tmp.unlink(missing_ok=True)
        owner.release()
        if not done:
            remove_empty_dirs(created)
    try:
        write_file_record(path, command)
    except OSError as exc:
        raise InputError(f"{path.name} was written, but its record could not be ({exc.strerror or exc}); "
                         "without it a later --overwrite refuses the file", path=file_record_path(path),
                         fix="free space or permissions, then run the command again after removing the file "
                             "yourself") from None
    return path


def remove_tree(path: Path) -> None:
    """`rm -rf path` that never raises (used on error paths)."""
    shutil.rmtree(path, ignore_errors=True)
