"""Reading NumPy files the user gives (`cameras.npz`, `poses_bounds.npy`, depth maps) without pickles."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from mvgeo.common.errors import InputError

__all__ = ["load_numpy"]


def load_numpy(path: str | Path, *, fix: str):
    """`np.load(path, allow_pickle=False)`: an array (`.npy`) or a lazy archive (`.npz`).

    Raises:
        InputError: naming the file, when it cannot be read (with the system's reason) or is not a NumPy
            file (damaged, or another format; NumPy's own message for the latter suggests loading it as a
            pickle, which a file from elsewhere must never be); `fix` is the advice for that case.
    """
    path = Path(path)
    try:
        return np.load(path, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"cannot read this file ({exc.strerror or exc})", path=path,
                         fix="check that it exists and is readable") from exc
    except (ValueError, EOFError, zipfile.BadZipFile) as exc:
        kind = ".npz archive" if path.suffix.lower() == ".npz" else ".npy file"
        raise InputError(f"not a NumPy {kind}, or a damaged one", path=path, fix=fix) from exc
