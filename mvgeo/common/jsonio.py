"""Reading the small JSON files users hand us (`split.json`, ...) with typed errors.

Imports only the standard library.
"""

from __future__ import annotations

import json
from pathlib import Path

from mvgeo.common.errors import InputError

__all__ = ["read_json_object"]


def read_json_object(path: str | Path, *, fix: str) -> dict:
    """The JSON object in the UTF-8 file `path`.

    Raises:
        InputError: naming `path` and `fix`, when the file cannot be read, is not UTF-8 text, is not valid
            JSON (or is nested too deeply to parse), or holds something other than an object.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_bytes())
    except OSError as exc:
        raise InputError(f"cannot read {path.name} ({exc.strerror})", path=path, fix=fix) from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{path.name} is not UTF-8 text (byte {exc.start} cannot be decoded)", path=path,
                         fix=fix) from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"{path.name} is not valid JSON ({exc})", path=path, fix=fix) from exc
    except RecursionError:
        raise InputError(f"{path.name} is not valid JSON (nested too deeply)", path=path, fix=fix) from None
    if not isinstance(data, dict):
        raise InputError(f"{path.name} holds a {type(data).__name__}, not an object", path=path, fix=fix)
    return data
