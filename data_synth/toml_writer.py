"""A minimal TOML writer for resolved scene specs (stdlib `tomllib` only reads).

Supports what scene files use: tables, arrays of tables, strings, booleans,
integers, floats and (nested) arrays of those. `tomllib.loads(dumps(d)) == d`
for such dicts (floats are written with `repr`, which round-trips exactly).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return "inf" if v > 0 else ("-inf" if v < 0 else "nan")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)  # a valid TOML basic string
    if isinstance(v, Sequence):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _key(k: str) -> str:
    if k and all(c.isalnum() or c in "-_" for c in k):
        return k
    return json.dumps(k)


def _is_table_array(v: Any) -> bool:
    return isinstance(v, Sequence) and not isinstance(v, str) and len(v) > 0 and all(
        isinstance(x, Mapping) for x in v)


def dumps(data: Mapping[str, Any]) -> str:
    """Serialise a dict of TOML-compatible values."""
    lines: list[str] = []
    _emit(data, [], lines)
    return "\n".join(lines).strip() + "\n"


def _emit(table: Mapping[str, Any], prefix: list[str], lines: list[str]) -> None:
    scalars = {k: v for k, v in table.items() if not isinstance(v, Mapping) and not _is_table_array(v)}
    for k, v in scalars.items():
        lines.append(f"{_key(k)} = {_value(v)}")
    for k, v in table.items():
        if isinstance(v, Mapping):
            path = prefix + [k]
            lines.append("")
            lines.append("[" + ".".join(_key(p) for p in path) + "]")
            _emit(v, path, lines)
        elif _is_table_array(v):
            path = prefix + [k]
            for item in v:
                lines.append("")
                lines.append("[[" + ".".join(_key(p) for p in path) + "]]")
                _emit(item, path, lines)
