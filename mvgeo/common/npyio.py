"""Reading NumPy files the user gives (`cameras.npz`, `poses_bounds.npy`, depth maps) without pickles."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from mvgeo.common.errors import InputError

__all__ = ["load_numpy"]


def load_numpy(path: str | Path, *, fix: str):
    """`np.load(path, allow_pickle=False)`: an array for a `.npy` name, a lazy archive for a `.npz` one.

    Raises:
        InputError: naming the file, when it cannot be read (with the system's reason), is not a NumPy
            file (damaged, or another format; NumPy's own message for the latter suggests loading it as a
            pickle, which a file from elsewhere must never be), or is the other kind than its name says;
            `fix` is the advice for those cases.
    """
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"cannot read this file ({exc.strerror or exc})", path=path,
                         fix="check that it exists and is readable") from exc
    except (ValueError, EOFError, zipfile.BadZipFile) as exc:
        kind = ".npz archive" if path.suffix.lower() == ".npz" else ".npy file"
        raise InputError(f"not a NumPy {kind}, or a damaged one", path=path, fix=fix) from exc
    archive = isinstance(data, np.lib.npyio.NpzFile)
    if path.suffix.lower() == ".npz" and not archive:
        raise InputError("holds a single array, not an .npz archive", path=path, fix=fix)
    if path.suffix.lower() == ".npy" and archive:
        data.close()
        raise InputError("is an .npz archive, not a single .npy array", path=path, fix=fix)
    return data
