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
   (its recorded summary is returned);
3. otherwise the record is deleted first, `fn` runs in a temporary sibling
   folder (removed if `fn` raises), the size and sha256 of every output file
   (every non-hidden file inside an output folder) are taken there, each output
   replaces the old one with an atomic rename, and the record is written last
   (atomically).

So a stage's outputs are complete exactly when its record holds the current
key and they hash as recorded: a crash at any point leaves either no record
(the stage re-runs) or the new one, and a missing, truncated or edited output
makes its stage run again.

Downstream stages follow through their keys, not through a flag held by the
runner: a stage's key contains the recorded output digest of each upstream
stage, so when a re-run upstream stage writes outputs that differ from before
(different bytes), every stage after it gets a new key and runs again, also in
a later process after an interruption. When the re-run writes the very bytes
the damaged files had before, the stages after it read exactly what they read
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
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from eval.pipeline.hashing import file_sha256, hash_json, hash_path, source_digest, tree_files
from mvgeo.common.atomic import atomic_write_text
from mvgeo.common.errors import DgsError
from mvgeo.common.timing import StageTimer

__all__ = ["RECORD_DIR", "StageContext", "StageFn", "StageResult", "StageRunner", "StageSpec", "code_digests",
           "output_manifest", "settings_json", "verify_outputs"]

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

    def key(self) -> str:
        """sha256 of name, settings, seed, hashed inputs' contents, code, and upstream keys and outputs."""
        return hash_json({
            "format": STAGE_FORMAT_VERSION,
            "name": self.name,
            "outputs": list(self.outputs),
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
        outputs: output name -> committed path.
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


def _record_path(spec: StageSpec) -> Path:
    return spec.stage_dir / RECORD_DIR / f"{spec.name}.json"


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _replace(src: Path, dst: Path) -> None:
    """Move `src` onto `dst` (file or folder); the old `dst` is renamed away first, then removed."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    old = None
    if dst.exists() or dst.is_symlink():
        old = dst.parent / f".{dst.name}.old-{uuid.uuid4().hex[:8]}"
        os.replace(dst, old)
    os.replace(src, dst)
    if old is not None:
        _remove(old)


def _reusable(spec: StageSpec, key: str, record: Path) -> tuple[dict | None, str]:
    """(the record, "") when the stage's committed outputs can be reused for `key`, else (None, why not)."""
    if not record.is_file():
        return None, "no record"
    try:
        rec = json.loads(record.read_text())
    except (OSError, json.JSONDecodeError):
        return None, "unreadable record"
    if not isinstance(rec, dict) or rec.get("key") != key:
        return None, "settings, inputs, code or upstream outputs changed"
    manifest = rec.get("manifest")
    if not isinstance(manifest, Mapping) or set(manifest.get("outputs", {})) != set(spec.outputs):
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
    """

    def __init__(self, *, timer: StageTimer | None = None, force: bool = False):
        self.timer = timer if timer is not None else StageTimer()
        self.force = force
        self.results: list[StageResult] = []

    def run(self, spec: StageSpec, *, label: str | None = None) -> StageResult:
        """Run `spec` unless its outputs are complete and unchanged for its key; see the module docstring.

        Args:
            spec: the stage.
            label: timer/log label (default `spec.name`).

        Raises:
            DgsError: the function did not write a declared output, or returned a non-JSON-able summary.
            Whatever the stage function raises (outputs and record are then untouched).
        """
        label = label or spec.name
        key = spec.key()
        record = _record_path(spec)
        outputs = {o: spec.stage_dir / o for o in spec.outputs}
        if not self.force:
            rec, why = _reusable(spec, key, record)
            if rec is not None:
                _log.info("stage %s: complete (outputs checked), skipped", label)
                result = StageResult(spec.name, key, outputs, rec.get("summary", {}), True,
                                     float(rec.get("seconds", 0.0)), hash_json(rec["manifest"]))
                self.results.append(result)
                return result
            if why.startswith("output check"):
                _log.warning("stage %s: %s; running it again", label, why)
            elif record.is_file():
                _log.info("stage %s: %s; running it again", label, why)
        spec.stage_dir.mkdir(parents=True, exist_ok=True)
        _remove(record)
        for stale in spec.stage_dir.glob(f".{spec.name}.work-*"):  # left by a killed run
            _remove(stale)
        work = Path(tempfile.mkdtemp(prefix=f".{spec.name}.work-", dir=spec.stage_dir))
        try:
            settings = dict(spec.settings) if isinstance(spec.settings, Mapping) else spec.settings
            ctx = StageContext(spec.name, work, dict(spec.inputs), settings, spec.seed)
            start = time.perf_counter()
            with self.timer.stage(label):
                summary = dict(spec.fn(ctx) or {})
            seconds = time.perf_counter() - start
            missing = [o for o in spec.outputs if not (work / o).exists()]
            if missing:
                raise DgsError(f"stage {label} did not write its declared outputs {missing} "
                               f"(a bug in the stage function)")
            manifest = output_manifest(work, spec.outputs)
            try:
                record_text = json.dumps({"key": key, "name": spec.name, "manifest": manifest,
                                          "code": code_digests(spec.fn, spec.code),
                                          "seconds": round(seconds, 4), "seed": spec.seed,
                                          "settings": settings_json(spec.settings), "summary": summary},
                                         indent=2, sort_keys=True)
            except TypeError as exc:
                raise DgsError(f"stage {label} returned a summary that is not JSON-able: {exc}") from exc
            for o in spec.outputs:
                _replace(work / o, outputs[o])
            atomic_write_text(record, record_text + "\n")
        finally:
            _remove(work)
        result = StageResult(spec.name, key, outputs, summary, False, seconds, hash_json(manifest))
        self.results.append(result)
        return result
