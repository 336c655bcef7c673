"""Content hashes that key the pipeline's stages and check their outputs (sha256, hex)."""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import json
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

from mvgeo.common.digest import file_sha256, update_with_file
from mvgeo.common.errors import DgsError

__all__ = ["SOURCE_SUFFIXES", "file_sha256", "hash_files", "hash_json", "hash_path", "source_digest",
           "tree_files"]

#: Files whose bytes make up a module's or package's source digest (the C++ kernels included).
SOURCE_SUFFIXES = (".py", ".cpp", ".h", ".c", ".cu")


def tree_files(folder: str | Path) -> list[Path]:
    """Every file under `folder`, recursively, sorted by relative path; hidden entries (a name starting
    with ".", at any depth) are left out."""
    folder = Path(folder)
    return sorted((p for p in folder.rglob("*") if p.is_file()
                   and not any(part.startswith(".") for part in p.relative_to(folder).parts)),
                  key=lambda p: p.relative_to(folder).as_posix())


def hash_files(files: Iterable[Path], *, root: Path | None = None) -> str:
    """Hash of the names (relative to `root`, else base names) and bytes of `files`, order-independent."""
    h = hashlib.sha256()
    items = sorted((p.relative_to(root).as_posix() if root else p.name, p) for p in map(Path, files))
    for name, path in items:
        h.update(name.encode("utf-8") + b"\0")
        update_with_file(h, path)
        h.update(b"\0")
    return h.hexdigest()


def hash_path(path: str | Path) -> str:
    """Hash of a file's bytes, or of every file under a folder (names and bytes; hidden entries skipped)."""
    path = Path(path)
    if path.is_file():
        return hash_files([path])
    return hash_files(tree_files(path), root=path)


def hash_json(obj: Mapping | list | str | int | float | bool | None) -> str:
    """Hash of a JSON-able value (keys sorted, so dict order does not matter)."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@functools.cache
def source_digest(name: str) -> str:
    """sha256 of the source of an importable module (its file) or package (every `SOURCE_SUFFIXES`
    file under its folder, subpackages included; `__pycache__` and hidden entries left out).

    Computed once per process and cached: the digest describes the code as it was when first asked
    for (`run_pipeline` asks at its start, before any stage runs), so sources edited while a run is
    in progress do not get recorded against results of the code loaded before. A new process (a
    resumed run) hashes the sources afresh.

    Raises:
        DgsError: `name` cannot be found or has no source file (e.g. code typed into `python -c`).
    """
    module = sys.modules.get(name)
    if module is not None:
        folders, file = getattr(module, "__path__", None), getattr(module, "__file__", None)
    else:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        folders = spec.submodule_search_locations if spec is not None else None
        file = spec.origin if spec is not None and spec.has_location else None
    if folders:
        root = Path(next(iter(folders)))
        files = [f for f in tree_files(root) if f.suffix in SOURCE_SUFFIXES and "__pycache__" not in f.parts]
        return hash_files(files, root=root)
    if file and Path(file).is_file():
        return file_sha256(file)
    raise DgsError(f"cannot hash the source of {name!r}: no module or package file found "
                   f"(stage functions must live in an importable module)")
