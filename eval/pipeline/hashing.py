"""Content hashes that key the pipeline's stages (sha256, hex)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from pathlib import Path

__all__ = ["hash_files", "hash_json", "hash_path"]

_CHUNK = 1 << 20


def _file_digest(path: Path, h) -> None:
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)


def hash_files(files: Iterable[Path], *, root: Path | None = None) -> str:
    """Hash of the names (relative to `root`, else base names) and bytes of `files`, order-independent."""
    h = hashlib.sha256()
    items = sorted((p.relative_to(root).as_posix() if root else p.name, p) for p in map(Path, files))
    for name, path in items:
        h.update(name.encode("utf-8") + b"\0")
        _file_digest(path, h)
        h.update(b"\0")
    return h.hexdigest()


def hash_path(path: str | Path) -> str:
    """Hash of a file's bytes, or of every file under a folder (names and bytes; hidden entries skipped)."""
    path = Path(path)
    if path.is_file():
        return hash_files([path])
    files = [p for p in path.rglob("*") if p.is_file()
             and not any(part.startswith(".") for part in p.relative_to(path).parts)]
    return hash_files(files, root=path)


def hash_json(obj: Mapping | list | str | int | float | bool | None) -> str:
    """Hash of a JSON-able value (keys sorted, so dict order does not matter)."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
