"""SHA-256 of files, read in blocks: the one implementation the output policy and the pipeline's stage
records share. Imports only the standard library."""

from __future__ import annotations

import hashlib
from pathlib import Path

__all__ = ["file_sha256", "update_with_file"]

_CHUNK = 1 << 20


def update_with_file(h: hashlib._Hash, path: str | Path) -> None:
    """Feed the bytes of the file `path` to the hash object `h`."""
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)


def file_sha256(path: str | Path) -> str:
    """sha256 (hex) of one file's bytes."""
    h = hashlib.sha256()
    update_with_file(h, path)
    return h.hexdigest()
