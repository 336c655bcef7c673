"""Resumable pipeline stages: keyed by a hash of inputs, settings and code, committed atomically,
checked before reuse.

A stage is a function `fn(ctx) -> summary` that reads its inputs from disk
(`ctx.inputs`) and writes its declared outputs (files or folders, paths
relative to the stage's folder) into a private work folder `ctx.work_dir`.
`StageRunner.run` then commits them:

1. the stage's key is the sha256 of its name, settings, seed, external
   inputs' contents, its code (below) and, for each upstream stage, that
   stage's key and the digest of the outputs it recorded;
2. if `stages/<name>.json` holds that key and every declared output still
   matches the record (same files, sizes and sha256), the stage is skipped
   (its recorded summary is returned). An output the spec declares optional
   (`StageSpec.optional`) may be absent: the record says which were written;
3. otherwise the committed outputs are checked to be the stage's own: every
   file in them (hidden ones included) must be one the record says the stage
   wrote, with the recorded sha256. A file the stage did not write, or one
   whose content changed, stops the run with `UnownedOutputError` before the
   stage changes anything (running it again would delete the file); a recorded
   file that is missing is fine (it is written again);
4. `fn` runs in a temporary sibling folder (removed if `fn` raises; the old
   outputs and their record stay as they were), the size and sha256 of every
   output file (every non-hidden file inside an output folder) are taken
   there, the ownership check is made again, a pending record owning both the
   old and the new files is written, each output replaces the old one with an
   atomic rename (the old one renamed aside first, then removed where it holds
   only files that record owns), and the record is written last (atomically).

So a stage's outputs are complete exactly when its record holds the current
key and they hash as recorded: a crash at any point leaves either the old
record with the old outputs, a pending record (the stage re-runs), or the new
one. A deleted output makes its stage run again; a changed or added file is
never overwritten or deleted, since it may be the user's.

Downstream stages follow through their keys, not through a flag held by the
runner: a stage's key contains the recorded output digest of each upstream
stage, so when a re-run upstream stage writes outputs that differ from before
(different bytes), every stage after it gets a new key and runs again, also in
a later process after an interruption. When the re-run writes the very bytes
the missing files had before, the stages after it read exactly what they read
the first time and their checked outputs are reused.

Code: one rule. The key includes `source_digest` of the module that defines
`fn` (its file) and of each module or package named in `StageSpec.code` (a
package counts with every source file in it), so a change anywhere in that
code re-runs the stage and, through the keys, the stages after it. The
product's stages name `eval.pipeline` and the component packages each calls
(`eval.pipeline.stages.STAGE_CODE`). The rule is coarse on purpose: an edit
that changes nothing a stage computes still re-runs it; an edit missed would
silently reuse stale results.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
import logging
import os
import re
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from eval.pipeline.hashing import file_sha256, hash_json, hash_path, source_digest, tree_files
from mvgeo.common.atomic import atomic_write_text
from mvgeo.common.errors import DgsError, InputError
from mvgeo.common.timing import StageTimer

__all__ = ["RECORD_DIR", "OwnershipCheck", "StageContext", "StageFn", "StageResult", "StageRunner", "StageSpec",
           "UnownedOutputError", "adopt_outputs", "check_outputs_owned", "code_digests", "commit_outputs",
           "commit_written",
           "output_manifest", "settings_json", "stage_work_dir", "unowned_outputs", "verify_outputs",
           "withdraw_outputs"]

_log = logging.getLogger(__name__)

#: Bump when the record format or the meaning of a key changes.
STAGE_FORMAT_VERSION = 2
#: Records live in `<stage folder>/stages/<stage name>.json`.
RECORD_DIR = "stages"


@dataclass(frozen=True)
class StageContext:
    """What a stage function gets.

    Attributes:
        name: the stage's name (e.g. "denoise").
        work_dir: empty folder; write every declared output here under its name.
        inputs: input name -> file or folder to read (external inputs and upstream outputs).
        settings: the stage's settings as given in `StageSpec.settings`: a frozen dataclass (the
            product's stages get theirs from `eval.pipeline.stage_settings`), or a copy of a mapping.
        seed: this stage's seed.
    """

    name: str
    work_dir: Path
    inputs: Mapping[str, Path]
    settings: Any
    seed: int


StageFn = Callable[[StageContext], Mapping[str, object]]


def _json_default(obj: object) -> object:
    """JSON form of the non-JSON values a settings dataclass may hold (numpy scalars, numpy and torch
    dtypes, torch devices, paths, enums); anything else is refused, so that no `repr` with a memory
    address enters a key."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.dtype) or (type(obj).__module__ == "torch" and type(obj).__name__ in ("dtype", "device")):
        return str(obj)  # "float32", "torch.float32", "cuda:0"
    if isinstance(obj, PurePath):
        return obj.as_posix()
    if isinstance(obj, enum.Enum):
        return obj.value
    raise TypeError(f"stage settings hold a {type(obj).__name__}, which has no canonical JSON form")


def settings_json(settings: object) -> dict[str, object]:
    """The canonical JSON form of a stage's settings, which enters its key and its record:
    `dataclasses.asdict` of a settings dataclass (nested dataclasses included) or a mapping's items,
    numpy scalars, dtypes, torch devices, paths and enums as plain values, keys sorted.

    Raises:
        TypeError: `settings` is neither a dataclass instance nor a mapping, or holds a value
            without a canonical JSON form (a bug in the caller).
    """
    if dataclasses.is_dataclass(settings) and not isinstance(settings, type):
        raw = dataclasses.asdict(settings)
    elif isinstance(settings, Mapping):
        raw = dict(settings)
    else:
        raise TypeError(f"stage settings must be a dataclass instance or a mapping, got {type(settings).__name__}")
    return json.loads(json.dumps(raw, default=_json_default, sort_keys=True, allow_nan=True))


def _module_of(fn: StageFn) -> str:
    """Name of the module that defines `fn` (through `functools.partial`)."""
    while isinstance(fn, functools.partial):
        fn = fn.func
    return getattr(fn, "__module__", None) or type(fn).__module__


def code_digests(fn: StageFn, code: Sequence[str] = ()) -> dict[str, str]:
    """The code a stage runs, as module/package name -> `source_digest`: `fn`'s own module and `code`."""
    return {name: source_digest(name) for name in sorted({_module_of(fn), *code})}


@dataclass(frozen=True)
class StageSpec:
    """One stage to run.

    Attributes:
        name: unique within `stage_dir` (also names the record file).
        stage_dir: folder the outputs are committed into (e.g. `OUT/round1`).
        fn: the stage function.
        outputs: output paths relative to `stage_dir`, each a file or a folder.
        inputs: input name -> path handed to `fn`.
        hashed_inputs: names in `inputs` whose *contents* enter the key
            (external inputs); the others are upstream outputs, covered by `upstream`.
        upstream: results of the stages whose outputs this one reads; their keys and
            recorded output digests enter this key.
        settings: handed to `fn` as `ctx.settings`; a frozen dataclass (or a mapping) whose
            canonical JSON form (`settings_json`) enters the key.
        seed: enters the key and is handed to `fn`.
        code: modules or packages the stage runs besides `fn`'s own module (e.g. `"splat"`);
            their source digests enter the key (the module docstring's rule).
        optional: those of `outputs` the function may leave unwritten (round 1's network, where the
            photos pass through undenoised); the record lists the outputs written, a committed optional
            output the run left unwritten is removed as the stage's own, and the stages after it see
            only the written ones (`StageResult.outputs`).
    """

    name: str
    stage_dir: Path
    fn: StageFn
    outputs: tuple[str, ...]
    inputs: Mapping[str, Path] = field(default_factory=dict)
    hashed_inputs: tuple[str, ...] = ()
    upstream: Sequence[StageResult] = ()
    settings: Any = field(default_factory=dict)
    seed: int = 0
    code: tuple[str, ...] = ()
    optional: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not set(self.optional) <= set(self.outputs):
            raise ValueError(f"stage {self.name}: optional outputs {list(self.optional)} are not all among its "
                             f"outputs {list(self.outputs)}")

    def key(self) -> str:
        """sha256 of name, settings, seed, hashed inputs' contents, code, and upstream keys and outputs."""
        return hash_json({
            "format": STAGE_FORMAT_VERSION,
            "name": self.name,
            "outputs": list(self.outputs),
            **({"optional": list(self.optional)} if self.optional else {}),
            "settings": settings_json(self.settings),
            "seed": self.seed,
            "inputs": {k: hash_path(self.inputs[k]) for k in sorted(self.hashed_inputs)},
            "upstream": {u.name: {"key": u.key, "outputs": u.outputs_digest} for u in self.upstream},
            "code": code_digests(self.fn, self.code),
        })


@dataclass(frozen=True)
class StageResult:
    """Outcome of `StageRunner.run`.

    Attributes:
        name: stage name.
        key: the stage key its outputs correspond to.
        outputs: output name -> committed path, for the outputs written (an optional one left unwritten is
            not in it).
        summary: what the stage function returned (JSON-able), as recorded.
        skipped: True when complete outputs with this key were found.
        seconds: wall time of the function when it ran (from the record when skipped).
        outputs_digest: `hash_json` of the outputs' manifest (`output_manifest`); it enters the
            keys of the stages that read these outputs.
    """

    name: str
    key: str
    outputs: Mapping[str, Path]
    summary: Mapping[str, object]
    skipped: bool
    seconds: float
    outputs_digest: str


def output_manifest(root: Path, outputs: Sequence[str]) -> dict[str, dict]:
    """What a stage wrote under `root`: `{"outputs": {output: "file" | "dir"},
    "files": {path relative to root: {"size": bytes, "sha256": hex}}}`, every file of an output
    folder included (hidden entries left out, as in `tree_files`)."""
    kinds: dict[str, str] = {}
    files: dict[str, dict[str, object]] = {}
    for o in outputs:
        path = root / o
        kinds[o] = "dir" if path.is_dir() else "file"
        for f in tree_files(path) if path.is_dir() else [path]:
            files[f.relative_to(root).as_posix()] = {"size": f.stat().st_size, "sha256": file_sha256(f)}
    return {"outputs": kinds, "files": files}


def verify_outputs(root: Path, manifest: Mapping[str, Mapping]) -> str | None:
    """None when the outputs under `root` are those `manifest` (`output_manifest`) records, else the
    first difference, in words. Sizes are compared before any file is hashed."""
    try:
        kinds, files = dict(manifest["outputs"]), dict(manifest["files"])
        found: dict[str, int] = {}
        for o, kind in kinds.items():
            path = root / o
            if not (path.is_dir() if kind == "dir" else path.is_file()):
                return f"{o} is missing" if not path.exists() else f"{o} is not a {kind}"
            for f in tree_files(path) if kind == "dir" else [path]:
                found[f.relative_to(root).as_posix()] = f.stat().st_size
        for name in sorted(files.keys() | found.keys()):
            if name not in found:
                return f"{name} is missing"
            if name not in files:
                return f"{name} was not written by the stage"
            if found[name] != files[name]["size"]:
                return f"{name} has {found[name]} bytes, {files[name]['size']} recorded"
        for name in sorted(files):
            if file_sha256(root / name) != files[name]["sha256"]:
                return f"{name} changed (sha256 differs from the record)"
    except (KeyError, TypeError, AttributeError):
        return "the record's output list is malformed"
    except OSError as exc:
        return f"an output cannot be read ({exc})"
    return None


class UnownedOutputError(InputError):
    """Stages' committed outputs hold files they did not write, or files they wrote whose content changed
    since; writing the outputs again would delete them, so nothing is changed.

    Attributes:
        stages: the stages' names.
        paths: the files concerned (each with why, e.g. ``"run/inputs/notes.txt (not written by the stage)"``).
    """

    def __init__(self, stages: str | Sequence[str], folder: Path, problems: Sequence[str]):
        self.stages = (stages,) if isinstance(stages, str) else tuple(stages)
        self.paths = tuple(problems)
        self.folder = Path(folder)
        names = ", ".join(repr(n) for n in self.stages)
        shown = "; ".join(problems[:8]) + (f"; and {len(problems) - 8} more" if len(problems) > 8 else "")
        which = f"stage {names}" if len(self.stages) == 1 else f"stages {names}"
        super().__init__(f"writing the outputs of {which} again would delete files in them that the run did "
                         f"not write or that changed since it wrote them: {shown}", path=folder,
                         fix="move these files out of the output folder (an output file that is missing is simply "
                             "written again), or choose another --out; the files named were left as they are")

    def __reduce__(self) -> tuple[type, tuple]:
        """Pickle with the constructor's arguments: one raised in a Ray task reaches the driver as itself."""
        return type(self), (self.stages, self.folder, list(self.paths))


class OwnershipCheck:
    """Runs several ownership checks and raises one `UnownedOutputError` naming every file they found.

    ``check(fn, *args)`` calls ``fn(*args)`` (e.g. `check_outputs_owned`) and keeps what its
    `UnownedOutputError` names; ``raise_if_any(folder)`` raises them together.
    """

    def __init__(self) -> None:
        self.stages: list[str] = []
        self.problems: list[str] = []

    def check(self, fn: Callable[..., None], *args: object, **kwargs: object) -> None:
        try:
            fn(*args, **kwargs)
        except UnownedOutputError as exc:
            self.stages.extend(n for n in exc.stages if n not in self.stages)
            self.problems.extend(exc.paths)

    def raise_if_any(self, folder: Path) -> None:
        if self.problems:
            raise UnownedOutputError(self.stages, folder, self.problems)


#: The file `stage_work_dir` puts in each work folder: what makes a leftover one the runner's to remove.
WORK_MARKER = ".denoise-gs-work"


def _record_file(stage_dir: Path, name: str) -> Path:
    return stage_dir / RECORD_DIR / f"{name}.json"


def _record_path(spec: StageSpec) -> Path:
    return _record_file(spec.stage_dir, spec.name)


def _read_record(record: Path) -> tuple[dict | None, str]:
    """(the record, "") or (None, why there is none usable)."""
    if not record.is_file():
        return None, "no record"
    try:
        rec = json.loads(record.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError):  # RecursionError: nested too deeply
        return None, "unreadable record"
    if not isinstance(rec, dict):
        return None, "unreadable record"
    return rec, ""


def completed_seconds(stage_dir: Path, name: str) -> float | None:
    """The seconds stage `name` took, from its record in `stage_dir`, where that record is a completed
    commit's; None where there is no record, it is not one this module wrote, or its commit was cut short
    (a pending record)."""
    rec, _ = _read_record(_record_file(stage_dir, name))
    seconds = None if rec is None or rec.get("pending") else rec.get("seconds")
    if isinstance(seconds, bool) or not isinstance(seconds, int | float):
        return None
    return float(seconds)


def _record_problems(stage_dir: Path, name: str) -> list[str]:
    """Why stage `name` may not write its record `stages/<name>.json` (as `unowned_outputs` words it): the
    record folder is not a folder, or a file of that name is not a record of stage `name` (a symbolic link,
    not a JSON object, or one naming another stage); [] when there is none or it is the stage's."""
    folder = stage_dir / RECORD_DIR
    if os.path.lexists(folder) and (folder.is_symlink() or not folder.is_dir()):
        return [f"{folder} (not a folder of stage records)"]
    path = _record_file(stage_dir, name)
    if not os.path.lexists(path):
        return []
    rec = None if path.is_symlink() else _read_record(path)[0]
    if rec is None or rec.get("name") != name:
        return [f"{path} (not a record written by the stage)"]
    return []


def _owned_files(rec: Mapping | None) -> dict[str, frozenset[str]]:
    """Path relative to the stage folder -> the sha256 values the stage wrote there, by its record:
    `owned` (every file, hidden ones included; a pending record's holds the old and the new files), else
    the manifest's files (records written before `owned` existed). Empty for no or a malformed record."""
    if rec is None:
        return {}
    try:
        owned = rec.get("owned")
        if isinstance(owned, Mapping):
            return {str(k): frozenset(str(h) for h in v) for k, v in owned.items() if isinstance(v, list)}
        return {str(k): frozenset([str(v["sha256"])]) for k, v in dict(rec["manifest"]["files"]).items()}
    except (KeyError, TypeError, AttributeError):
        return {}


def _entries(root: Path, outputs: Sequence[str]) -> Iterator[tuple[str, Path]]:
    """(path relative to `root`, path) of every entry under `root`'s `outputs` that is not a folder: files,
    symbolic links (to folders too: they are not followed) and anything else, hidden ones included.

    Raises:
        OSError: a folder cannot be listed.
    """

    def fail(exc: OSError) -> None:
        raise exc

    for o in outputs:
        path = root / o
        if not os.path.lexists(path):
            continue
        if not path.is_dir() or path.is_symlink():
            yield o, path
            continue
        for dirpath, dirnames, filenames in os.walk(path, onerror=fail):
            folder = Path(dirpath)
            for n in sorted(dirnames):
                if (folder / n).is_symlink():
                    yield (folder / n).relative_to(root).as_posix(), folder / n
            for n in sorted(filenames):
                yield (folder / n).relative_to(root).as_posix(), folder / n


def unowned_outputs(stage_dir: Path, outputs: Sequence[str], owned: Mapping[str, frozenset[str]]) -> list[str]:
    """The entries under `stage_dir`'s `outputs` that are not files `owned` records with their current content,
    each as ``"<path> (why)"`` (the path as `stage_dir` is given); missing recorded files are no problem."""
    problems = []
    try:
        for rel, path in _entries(stage_dir, outputs):
            shas = owned.get(rel)
            if path.is_symlink() or not path.is_file() or not shas:
                problems.append(f"{path} (not written by the stage)")
            elif file_sha256(path) not in shas:
                problems.append(f"{path} (changed since the stage wrote it)")
    except OSError as exc:
        problems.append(f"{exc.filename or stage_dir} (cannot be read: {exc.strerror or exc})")
    return problems


def check_outputs_owned(stage_dir: Path, name: str, outputs: Sequence[str], *, defer_hidden: bool = False) -> None:
    """Raise `UnownedOutputError` when the committed `outputs` of stage `name` in `stage_dir` hold anything its
    record (`stages/<name>.json`) does not say it wrote, as it wrote it (see `unowned_outputs`); without a
    readable record, every existing file in them counts as not written by the stage.

    With `defer_hidden`, outputs that are complete by the record (`verify_outputs`) pass: all they can hold
    besides the stage's files are hidden entries (e.g. a file manager's `.DS_Store`), which matter only if
    the stage runs again, and `StageRunner.run` checks them then (before the stage changes anything; stages
    before it may have run by then).
    """
    problems = _record_problems(stage_dir, name)
    if problems:
        raise UnownedOutputError(name, stage_dir, problems)
    rec, _ = _read_record(_record_file(stage_dir, name))
    manifest = rec.get("manifest") if rec is not None else None
    if (defer_hidden and isinstance(manifest, Mapping) and isinstance(manifest.get("outputs"), Mapping)
            and set(manifest["outputs"]) == set(outputs) and verify_outputs(stage_dir, manifest) is None):
        return
    problems = unowned_outputs(stage_dir, outputs, _owned_files(rec))
    if problems:
        raise UnownedOutputError(name, stage_dir, problems)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _retired_name(output: str, tag: str) -> str:
    """Where `commit_outputs` moves the committed `output` (relative to the stage folder) while the new one
    takes its place: a hidden sibling `.<name>.old-<tag>`."""
    out = PurePath(output)
    return (out.parent / f".{out.name}.old-{tag}").as_posix()


def _replace(src: Path, dst: Path, old: Path) -> None:
    """Move `src` onto `dst` (file or folder); the old `dst` is renamed to `old` first (removed by the caller,
    `_clear_retired`)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists() or dst.is_symlink():
        os.replace(dst, old)
    os.replace(src, dst)


def _clear_retired(stage_dir: Path, rec: Mapping | None, outputs: Sequence[str]) -> None:
    """Remove the old outputs a commit moved aside to their retired names (`_retired_name`; this commit's, or
    a killed one's): those the pending record `rec` names, and only when every file in them is one the
    record owns, as it wrote it (else they are left; they are hidden and block nothing)."""
    retired = rec.get("retired") if rec is not None and rec.get("pending") else None
    if not isinstance(retired, Mapping):
        return
    owned = _owned_files(rec)
    for output, name in retired.items():
        tag = name.rsplit("-", 1)[-1] if isinstance(name, str) else ""
        if output not in outputs or not re.fullmatch(r"[0-9a-f]{8}", tag) or name != _retired_name(output, tag):
            continue  # only the stage's own outputs' retired names (a record edited by hand names others)
        path = stage_dir / name
        if not os.path.lexists(path):
            continue
        try:
            entries = [(str(output) + rel[len(name):], p) for rel, p in _entries(stage_dir, [name])]
            ours = all(not p.is_symlink() and p.is_file() and file_sha256(p) in owned.get(rel, ())
                       for rel, p in entries)
        except OSError:
            ours = False
        if ours:
            _remove(path)
        else:
            _log.warning("left %s: the old output a killed run moved there holds files it did not write", path)


@contextmanager
def stage_work_dir(stage_dir: Path, name: str) -> Iterator[Path]:
    """A new hidden folder `stage_dir/.<name>.work-*` for a stage's outputs (holding only the marker
    `WORK_MARKER`), removed when the block ends. Those a killed run left are removed first: folders of that
    name pattern that hold the marker (a folder of the user's with a similar name does not)."""
    stage_dir.mkdir(parents=True, exist_ok=True)
    ours = re.compile(rf"\.{re.escape(name)}\.work-[a-z0-9_]{{8}}")  # `tempfile.mkdtemp`'s 8 characters
    for stale in stage_dir.glob(f".{name}.work-*"):
        if (ours.fullmatch(stale.name) and stale.is_dir() and not stale.is_symlink()
                and (stale / WORK_MARKER).is_file()):
            _remove(stale)
    work = Path(tempfile.mkdtemp(prefix=f".{name}.work-", dir=stage_dir))
    try:
        (work / WORK_MARKER).write_text(f"stage {name}, pid {os.getpid()}\n")
        yield work
    finally:
        _remove(work)


def commit_outputs(stage_dir: Path, name: str, outputs: Sequence[str], work: Path, record: Mapping[str, object],
                   manifest: Mapping[str, Mapping] | None = None) -> None:
    """Move the outputs written in `work` into `stage_dir` and write the record `stages/<name>.json`.

    Each of `outputs` present in `work` replaces the committed one (atomic rename); one absent from `work`
    is removed from `stage_dir`. First the committed outputs are checked to be the stage's own
    (`check_outputs_owned`), and a pending record owning both the old and the new files is written, so
    that a crash while they are replaced leaves files the next run knows as its own. The record written
    last is `record` plus `owned` (every file written, hidden ones included).

    Args:
        manifest: `output_manifest(work, ...)` when the caller has it (its sha256 values are reused).

    Raises:
        UnownedOutputError: the committed outputs hold files the stage did not write or that changed.
    """
    rec_path = _record_file(stage_dir, name)
    old_rec, _ = _read_record(rec_path)
    old = _owned_files(old_rec)
    problems = _record_problems(stage_dir, name) + unowned_outputs(stage_dir, outputs, old)
    if problems:
        raise UnownedOutputError(name, stage_dir, problems)
    _clear_retired(stage_dir, old_rec, outputs)
    known = {k: v["sha256"] for k, v in (manifest or {}).get("files", {}).items()}
    new = _owned_now(work, outputs, known)
    pending = {rel: sorted(set(new.get(rel, [])) | old.get(rel, frozenset())) for rel in new.keys() | old.keys()}
    tag = uuid.uuid4().hex[:8]
    retired = {o: _retired_name(o, tag) for o in outputs if os.path.lexists(work / o)}
    pending_rec = {"name": name, "pending": True, "owned": pending, "retired": retired}
    _write_record(rec_path, pending_rec)
    for o in outputs:
        if o in retired:
            _replace(work / o, stage_dir / o, stage_dir / retired[o])
        elif os.path.lexists(stage_dir / o):
            _remove(stage_dir / o)
    # The old outputs are removed only as the pending record owns them: a file put into one after the check
    # above and before its rename is kept (under the hidden retired name, with a warning).
    _clear_retired(stage_dir, pending_rec, outputs)
    _write_record(rec_path, {**record, "owned": new})


def _owned_now(root: Path, outputs: Sequence[str], known: Mapping[str, str] | None = None) -> dict[str, list[str]]:
    """The `owned` map of a record for the files now under `root`'s `outputs` (sha256 from `known` where
    given, else hashed)."""
    known = known or {}
    return {rel: [known.get(rel) or file_sha256(path)] for rel, path in _entries(root, outputs) if path.is_file()}


def _write_record(path: Path, record: Mapping[str, object]) -> None:
    atomic_write_text(path, json.dumps(record, indent=2, sort_keys=True) + "\n")


def commit_written(folder: Path, name: str, outputs: Sequence[str], write: Callable[[Path], None],
                   record: Mapping[str, object] | None = None) -> None:
    """Write `outputs` (paths relative to `folder`) with `write(work)` into a new hidden work folder of
    `folder` (`stage_work_dir`), then commit them into `folder` with the record `folder/stages/<name>.json`
    (`commit_outputs`; `record`'s fields added to it); an output `write` did not write is removed from
    `folder`. What a pipeline stage's run does, for outputs that are not a stage's (a report, results).

    Raises:
        UnownedOutputError: `folder`'s `outputs` hold files the record does not list, or listed files whose
            content changed (checked before `write` runs and again before the commit; nothing is changed).
        Whatever `write` raises (the work folder is removed; `folder` is unchanged).
    """
    folder = Path(folder)
    check_outputs_owned(folder, name, outputs)
    with stage_work_dir(folder, name) as work:
        write(work)
        written = [o for o in outputs if os.path.lexists(work / o)]
        manifest = output_manifest(work, written)
        commit_outputs(folder, name, outputs, work, {**(record or {}), "name": name, "manifest": manifest},
                       manifest)


def adopt_outputs(stage_dir: Path, name: str, outputs: Sequence[str]) -> None:
    """Record the files now in `stage_dir`'s `outputs` as stage `name`'s own (`stages/<name>.json`, as
    `commit_outputs` records them), for outputs a caller has just verified to be its own by other means.

    Raises:
        UnownedOutputError: a file of the record's name is not a record of stage `name` (nothing is written).
    """
    problems = _record_problems(stage_dir, name)
    if problems:
        raise UnownedOutputError(name, stage_dir, problems)
    _write_record(_record_file(stage_dir, name), {"name": name, "owned": _owned_now(stage_dir, outputs)})


def withdraw_outputs(stage_dir: Path, name: str, outputs: Sequence[str]) -> bool:
    """Remove the committed `outputs` of stage `name`, then its record, after `check_outputs_owned`.

    A crash in between leaves the record with some outputs missing, which the next run writes again.
    Returns True when anything was removed.

    Raises:
        UnownedOutputError: they hold files the stage did not write or that changed (nothing is removed).
    """
    check_outputs_owned(stage_dir, name, outputs)
    _clear_retired(stage_dir, _read_record(_record_file(stage_dir, name))[0], outputs)
    removed = False
    for o in outputs:
        if os.path.lexists(stage_dir / o):
            _remove(stage_dir / o)
            removed = True
    record = _record_file(stage_dir, name)
    if record.is_file():
        record.unlink()
        removed = True
    return removed


def _reusable(spec: StageSpec, key: str, rec: dict | None, why: str) -> tuple[dict | None, str]:
    """(the record, "") when the stage's committed outputs can be reused for `key`, else (None, why not)."""
    if rec is None:
        return None, why
    if rec.get("key") != key:
        return None, "settings, inputs, code or upstream outputs changed"
    manifest = rec.get("manifest")
    recorded = set(manifest.get("outputs", {})) if isinstance(manifest, Mapping) else None
    if recorded is None or not set(spec.outputs) - set(spec.optional) <= recorded <= set(spec.outputs):
        return None, "the record does not list the declared outputs"
    problem = verify_outputs(spec.stage_dir, manifest)
    if problem is not None:
        return None, f"output check: {problem}"
    return rec, ""


class StageRunner:
    """Runs `StageSpec`s, skipping complete ones, timing each with a `StageTimer`.

    Args:
        timer: receives the seconds of every stage that runs, under `"<label>/<name>"`.
        force: re-run every stage even when its outputs are complete.
        before_change: called with a stage's spec when it is about to run (it will not be skipped and its
            outputs are the stage's own), before its function runs; `run_pipeline` withdraws the run's
            published result there.
    """

    def __init__(self, *, timer: StageTimer | None = None, force: bool = False,
                 before_change: Callable[[StageSpec], None] | None = None):
        self.timer = timer if timer is not None else StageTimer()
        self.force = force
        self.before_change = before_change
        self.results: list[StageResult] = []

    def run(self, spec: StageSpec, *, label: str | None = None) -> StageResult:
        """Run `spec` unless its outputs are complete and unchanged for its key; see the module docstring.

        Args:
            spec: the stage.
            label: timer/log label (default `spec.name`).

        Raises:
            UnownedOutputError: the stage must run, but its committed outputs hold files it did not write
                or that changed since (checked before the function runs and again before the commit;
                nothing of the stage's is changed).
            DgsError: the function did not write a declared output, or returned a non-JSON-able summary.
            Whatever the stage function raises (outputs and record are then untouched).
        """
        label = label or spec.name
        key = spec.key()
        record = _record_path(spec)
        old, why = _read_record(record)
        if not self.force:
            rec, why = _reusable(spec, key, old, why)
            if rec is not None:
                _log.info("stage %s: complete (outputs checked), skipped", label)
                outputs = {o: spec.stage_dir / o for o in spec.outputs if o in rec["manifest"]["outputs"]}
                result = StageResult(spec.name, key, outputs, rec.get("summary", {}), True,
                                     float(rec.get("seconds", 0.0)), hash_json(rec["manifest"]))
                self.results.append(result)
                return result
        problems = (_record_problems(spec.stage_dir, spec.name)
                    + unowned_outputs(spec.stage_dir, spec.outputs, _owned_files(old)))
        if problems:
            raise UnownedOutputError(spec.name, spec.stage_dir, problems)
        if not self.force:
            if why.startswith("output check"):
                _log.warning("stage %s: %s; running it again", label, why)
            elif record.is_file():
                _log.info("stage %s: %s; running it again", label, why)
        if self.before_change is not None:
            self.before_change(spec)
        with stage_work_dir(spec.stage_dir, spec.name) as work:
            settings = dict(spec.settings) if isinstance(spec.settings, Mapping) else spec.settings
            ctx = StageContext(spec.name, work, dict(spec.inputs), settings, spec.seed)
            start = time.perf_counter()
            with self.timer.stage(label):
                summary = dict(spec.fn(ctx) or {})
            seconds = time.perf_counter() - start
            missing = [o for o in spec.outputs if not (work / o).exists() and o not in spec.optional]
            if missing:
                raise DgsError(f"stage {label} did not write its declared outputs {missing} "
                               f"(a bug in the stage function)")
            written = [o for o in spec.outputs if (work / o).exists()]
            manifest = output_manifest(work, written)
            body = {"key": key, "name": spec.name, "manifest": manifest, "code": code_digests(spec.fn, spec.code),
                    "seconds": round(seconds, 4), "seed": spec.seed, "settings": settings_json(spec.settings),
                    "summary": summary}
            try:
                json.dumps(body)
            except TypeError as exc:
                raise DgsError(f"stage {label} returned a summary that is not JSON-able: {exc}") from exc
            commit_outputs(spec.stage_dir, spec.name, spec.outputs, work, body, manifest)
        outputs = {o: spec.stage_dir / o for o in written}
        result = StageResult(spec.name, key, outputs, summary, False, seconds, hash_json(manifest))
        self.results.append(result)
        return result
