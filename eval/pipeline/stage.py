"""Resumable pipeline stages: keyed by a hash of inputs and settings, committed atomically.

A stage is a function `fn(ctx) -> summary` that reads its inputs from disk
(`ctx.inputs`) and writes its declared outputs (files or folders, paths
relative to the stage's folder) into a private work folder `ctx.work_dir`.
`StageRunner.run` then commits them:

1. the stage's key is the sha256 of its name, settings, external inputs'
   contents and its upstream stages' keys;
2. if `stages/<name>.json` exists with that key and every declared output
   exists, the stage is skipped (its recorded summary is returned);
3. otherwise the record is deleted first, `fn` runs in a temporary sibling
   folder (removed if `fn` raises), each output replaces the old one with an
   atomic rename, and the record is written last (atomically).

So a stage's outputs are complete exactly when its record holds the current
key: a crash at any point leaves either no record (the stage re-runs) or the
new one. Code changes are not part of the key; re-run with `force=True`
after changing a stage's code.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from eval.pipeline.hashing import hash_json, hash_path
from mvgeo.common.atomic import atomic_write_text
from mvgeo.common.errors import DgsError
from mvgeo.common.timing import StageTimer

__all__ = ["RECORD_DIR", "StageContext", "StageFn", "StageResult", "StageRunner", "StageSpec"]

_log = logging.getLogger(__name__)

#: Bump when the record format or the meaning of a key changes.
STAGE_FORMAT_VERSION = 1
#: Records live in `<stage folder>/stages/<stage name>.json`.
RECORD_DIR = "stages"


@dataclass(frozen=True)
class StageContext:
    """What a stage function gets.

    Attributes:
        name: the stage's name (e.g. "denoise").
        work_dir: empty folder; write every declared output here under its name.
        inputs: input name -> file or folder to read (external inputs and upstream outputs).
        settings: the JSON-able settings that entered the key (read-only view).
        seed: this stage's seed.
    """

    name: str
    work_dir: Path
    inputs: Mapping[str, Path]
    settings: Mapping[str, object]
    seed: int


StageFn = Callable[[StageContext], Mapping[str, object]]


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
        upstream: results of the stages whose outputs this one reads; their keys enter this key.
        settings: JSON-able settings that enter the key.
        seed: enters the key and is handed to `fn`.
    """

    name: str
    stage_dir: Path
    fn: StageFn
    outputs: tuple[str, ...]
    inputs: Mapping[str, Path] = field(default_factory=dict)
    hashed_inputs: tuple[str, ...] = ()
    upstream: Sequence[StageResult] = ()
    settings: Mapping[str, object] = field(default_factory=dict)
    seed: int = 0

    def key(self) -> str:
        """sha256 of name, settings, seed, hashed inputs' contents and upstream keys."""
        return hash_json({
            "format": STAGE_FORMAT_VERSION,
            "name": self.name,
            "outputs": list(self.outputs),
            "settings": dict(self.settings),
            "seed": self.seed,
            "inputs": {k: hash_path(self.inputs[k]) for k in sorted(self.hashed_inputs)},
            "upstream": {u.name: u.key for u in self.upstream},
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
    """

    name: str
    key: str
    outputs: Mapping[str, Path]
    summary: Mapping[str, object]
    skipped: bool
    seconds: float


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
        """Run `spec` unless its outputs are complete for its key; see the module docstring.

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
        if not self.force and record.is_file():
            try:
                rec = json.loads(record.read_text())
            except (OSError, json.JSONDecodeError):
                rec = None
            if rec and rec.get("key") == key and all(p.exists() for p in outputs.values()):
                _log.info("stage %s: complete, skipped", label)
                result = StageResult(spec.name, key, outputs, rec.get("summary", {}), True,
                                     float(rec.get("seconds", 0.0)))
                self.results.append(result)
                return result
        spec.stage_dir.mkdir(parents=True, exist_ok=True)
        _remove(record)
        for stale in spec.stage_dir.glob(f".{spec.name}.work-*"):  # left by a killed run
            _remove(stale)
        work = Path(tempfile.mkdtemp(prefix=f".{spec.name}.work-", dir=spec.stage_dir))
        try:
            ctx = StageContext(spec.name, work, dict(spec.inputs), dict(spec.settings), spec.seed)
            start = time.perf_counter()
            with self.timer.stage(label):
                summary = dict(spec.fn(ctx) or {})
            seconds = time.perf_counter() - start
            missing = [o for o in spec.outputs if not (work / o).exists()]
            if missing:
                raise DgsError(f"stage {label} did not write its declared outputs {missing} "
                               f"(a bug in the stage function)")
            try:
                record_text = json.dumps({"key": key, "name": spec.name, "outputs": list(spec.outputs),
                                          "seconds": round(seconds, 4), "seed": spec.seed,
                                          "settings": dict(spec.settings), "summary": summary},
                                         indent=2, sort_keys=True)
            except TypeError as exc:
                raise DgsError(f"stage {label} returned a summary that is not JSON-able: {exc}") from exc
            for o in spec.outputs:
                _replace(work / o, outputs[o])
            atomic_write_text(record, record_text + "\n")
        finally:
            _remove(work)
        result = StageResult(spec.name, key, outputs, summary, False, seconds)
        self.results.append(result)
        return result
