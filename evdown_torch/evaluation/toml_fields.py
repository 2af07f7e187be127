"""TOML values checked against typed dataclass fields: what ``evdown evaluate`` configs use.

Each table of a config maps onto a frozen dataclass (:mod:`.config`); :func:`section` builds
one from a parsed TOML table, so an unknown key or a value of the wrong type is an error that
names the key, never a silent default.
"""

from __future__ import annotations

import math
import sys
import types
import typing
from dataclasses import fields
from typing import Any

__all__ = ["section", "toml_loads"]


def _type_name(value: Any) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
            list: "an array", dict: "a table"}.get(type(value), type(value).__name__)


def _convert(key: str, value: Any, kind: Any) -> Any:
    """Check a TOML value against a field's annotation; arrays become tuples."""
    origin = typing.get_origin(kind)
    if origin in (typing.Union, types.UnionType):
        options = [k for k in typing.get_args(kind) if k is not type(None)]
        for option in options:
            try:
                return _convert(key, value, option)
            except TypeError:
                continue
        expected = " or ".join(_describe(option) for option in options)
        raise TypeError(f"{key} must be {expected}, got {_type_name(value)} ({value!r})")
    if origin is tuple:
        args = typing.get_args(kind)
        if not isinstance(value, list):
            raise TypeError(f"{key} must be {_describe(kind)}, got {_type_name(value)} ({value!r})")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(f"{key}[{i}]", v, args[0]) for i, v in enumerate(value))
        if len(value) != len(args):
            raise TypeError(f"{key} must be {_describe(kind)}, got {value!r}")
        return tuple(_convert(f"{key}[{i}]", v, a) for i, (v, a) in enumerate(zip(value, args)))
    ok = {
        bool: isinstance(value, bool),
        int: isinstance(value, int) and not isinstance(value, bool),
        float: isinstance(value, (int, float)) and not isinstance(value, bool),
        str: isinstance(value, str),
    }.get(kind)
    if ok is None:  # pragma: no cover - a field type this loader does not know
        raise TypeError(f"{key}: unsupported field type {kind!r}")
    if not ok:
        raise TypeError(f"{key} must be {_describe(kind)}, got {_type_name(value)} ({value!r})")
    if kind is float:
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"{key} must be finite, got {value!r}")
    return value


def _describe(kind: Any) -> str:
    origin = typing.get_origin(kind)
    if origin is tuple:
        args = typing.get_args(kind)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"an array whose items are each {_describe(args[0])}"
        return f"an array of {len(args)} items, each {_describe(args[0])}"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(k) for k in typing.get_args(kind) if k is not type(None))
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}[kind]


def section(cls: type, table: Any, where: str) -> Any:
    """Build dataclass ``cls`` from the TOML table ``[where]``, checking every key and type.

    Raises:
        ValueError: for an unknown key or a value out of range.
        TypeError: for a value of the wrong type.
    """
    if not isinstance(table, dict):
        raise TypeError(f"[{where}] must be a table, got {_type_name(table)} ({table!r})")
    hints = typing.get_type_hints(cls)
    known = [f.name for f in fields(cls)]
    for key in table:
        if key not in known:
            raise ValueError(f"unknown key {where}.{key}; [{where}] takes {known}")
    values = {key: _convert(f"{where}.{key}", value, hints[key]) for key, value in table.items()}
    return cls(**values)


def toml_loads(text: str) -> dict[str, Any]:
    """Parse TOML ``text`` (``tomllib``, or ``tomli`` before Python 3.11).

    Raises:
        ValueError: for invalid TOML.
        RuntimeError: without a TOML parser.
    """
    try:
        if sys.version_info >= (3, 11):
            import tomllib
        else:
            import tomli as tomllib
    except ModuleNotFoundError:
        raise RuntimeError(
            "reading TOML configs needs Python >= 3.11 (tomllib) or the tomli package"
        ) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ValueError(f"invalid TOML: {error}") from None
