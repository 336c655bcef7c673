"""A small typed-schema layer: TOML tables -> frozen dataclasses, errors with key paths.

A spec class is a dataclass whose fields carry their own constraints in
`field(metadata=...)` (made with `spec_field`). `from_table(cls, table, key=, path=)`
checks, for every key of `table`:

- the key is a field of `cls` (otherwise: unknown key, with the accepted keys);
- the value has the field's type (`bool`, `int`, `float` (ints accepted),
  `str`, `list[...]`/`tuple[...]` of those, a nested spec class, a list of
  spec classes, `X | None`);
- numbers lie in `range=(lo, hi)` (inclusive; `None` for open), strings in
  `choices=(...)`, sequences have `length=` entries;
- then the class's own `validated(key=, path=)` hook, if any, checks
  cross-field rules and returns the object with derived defaults filled in.

Every error is a `ConfigError` naming the file, the dotted key path
(`objects[2].radius`) and what is expected. No `eval`, no string-keyed option
dicts past this layer.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from mvgeo.common.errors import ConfigError


def spec_field(
    default: Any = dataclasses.MISSING,
    *,
    doc: str = "",
    range: tuple[float | None, float | None] | None = None,  # noqa: A002  (mirrors the metadata key)
    choices: tuple[str, ...] | None = None,
    length: int | tuple[int, ...] | None = None,
    item_length: int | tuple[int, ...] | None = None,
    default_factory: Any = dataclasses.MISSING,
) -> Any:
    """A dataclass field with validation metadata (see module docstring).

    `length` constrains the list itself, `item_length` the lists inside it
    (e.g. a list of RGB triples: `item_length=3`).
    """
    meta = {"doc": doc, "range": range, "choices": choices, "length": length, "item_length": item_length}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin in (types.UnionType, typing.Union):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin in (list, tuple):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return f"a list of {_type_name(args[0])}" if args else "a list"
    if tp is type(None):
        return "nothing"
    if dataclasses.is_dataclass(tp):
        return "a table"
    return {bool: "true/false", int: "an integer", float: "a number", str: "a string"}.get(tp, str(tp))


def _convert(value: Any, tp: Any, meta: Mapping[str, Any], key: str, path: Path | None) -> Any:
    origin = typing.get_origin(tp)
    if origin in (types.UnionType, typing.Union):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        non_none = [a for a in args if a is not type(None)]
        errors = []
        for arg in non_none:
            try:
                return _convert(value, arg, meta, key, path)
            except ConfigError as exc:
                errors.append(exc)
        if len(errors) == 1:
            raise errors[0]
        raise ConfigError(f"got {value!r}", key=key, path=path, expected=_type_name(tp))
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(f"got {type(value).__name__} {value!r}", key=key, path=path, expected="a table")
        return from_table(tp, value, key=key, path=path)
    if origin in (list, tuple):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"got {value!r}", key=key, path=path, expected=_type_name(tp))
        length = meta.get("length")
        if length is not None:
            allowed = (length,) if isinstance(length, int) else tuple(length)
            if len(value) not in allowed:
                raise ConfigError(f"has {len(value)} entries", key=key, path=path,
                                  expected=f"{' or '.join(map(str, allowed))} entries")
        (elem,) = [a for a in typing.get_args(tp) if a is not Ellipsis][:1] or [Any]
        inner_meta = {k: v for k, v in meta.items() if k not in ("length", "item_length")}
        inner_meta["length"] = meta.get("item_length")
        out = [_convert(v, elem, inner_meta, f"{key}[{i}]", path) for i, v in enumerate(value)]
        return tuple(out)
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"got {value!r}", key=key, path=path, expected="true or false")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"got {value!r}", key=key, path=path, expected="an integer")
        _check_range(value, meta, key, path)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"got {value!r}", key=key, path=path, expected="a number")
        value = float(value)
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(f"got {value!r}", key=key, path=path, expected="a finite number")
        _check_range(value, meta, key, path)
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"got {value!r}", key=key, path=path, expected="a string")
        choices = meta.get("choices")
        if choices is not None and value not in choices:
            raise ConfigError(f"got {value!r}", key=key, path=path, expected="one of " + ", ".join(choices))
        return value
    raise TypeError(f"schema: unsupported field type {tp!r} at {key}")  # a bug in a spec class


def _check_range(value: float, meta: Mapping[str, Any], key: str, path: Path | None) -> None:
    rng = meta.get("range")
    if rng is None:
        return
    lo, hi = rng
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        lo_s = "-inf" if lo is None else f"{lo:g}"
        hi_s = "inf" if hi is None else f"{hi:g}"
        raise ConfigError(f"{value!r} is out of range", key=key, path=path, expected=f"a value in [{lo_s}, {hi_s}]")


def join_key(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def from_table[T](cls: type[T], table: Mapping[str, Any], *, key: str = "", path: str | Path | None = None) -> T:
    """Validate a TOML table against the spec dataclass `cls` and build it.

    Args:
        cls: a dataclass whose fields use `spec_field` metadata.
        table: the parsed TOML table.
        key: the dotted key path of `table` in its file ("" for the root).
        path: the file, for error messages.

    Raises:
        ConfigError: unknown key, missing required key, wrong type or out-of-range value.
    """
    path = None if path is None else Path(path)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    for name in table:
        if name not in fields:
            raise ConfigError("unknown key", key=join_key(key, str(name)), path=path,
                              expected="one of " + ", ".join(sorted(fields)))
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        sub = join_key(key, name)
        if name in table:
            kwargs[name] = _convert(table[name], hints[name], f.metadata, sub, path)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError("missing required key", key=sub, path=path, expected=_type_name(hints[name]))
    obj = cls(**kwargs)
    validated = getattr(obj, "validated", None)
    if validated is not None:
        obj = validated(key=key, path=path)
    return obj


def to_table(obj: Any) -> Any:
    """The inverse of `from_table`: a dataclass -> plain dicts/lists (None values dropped)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {}
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if value is None:
                continue
            out[f.name] = to_table(value)
        return out
    if isinstance(obj, list | tuple):
        return [to_table(v) for v in obj]
    return obj
