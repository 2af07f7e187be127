"""Small text parsers and formatters shared by the command line and the tools behind it.

Internal (no stability promise), but the one home for these rules: the ``KEY=VALUE`` setting
syntax of ``evdown downscale --set`` and ``evdown bench --methods NAME:KEY=VALUE,...``, how a
factor is read from and written to text, and the two wordings of a warning (:class:`WordedWarning`).
"""

from __future__ import annotations

import ast
import re
from typing import Any

__all__ = ["WordedWarning", "format_factor", "parse_factor", "parse_setting", "parse_settings",
           "parse_value"]

class WordedWarning(UserWarning):
    """A warning whose text names the fix for a Python caller, with the command line's beside it.

    ``evdown`` prints :attr:`command_line` (``--sensor-size W H P``) where Python code reads
    the text (``sensor_size=(W, H, P)``).

    Attributes:
        command_line: the same warning in the command line's words.
    """

    def __init__(self, message: str, command_line: str | None = None) -> None:
        super().__init__(message)
        self.command_line = message if command_line is None else command_line


# A comma starts a new setting only where ``KEY=`` follows it, so tuples stay whole.
_SETTING_SPLIT = re.compile(r",\s*(?=[A-Za-z_][\w-]*\s*=)")


def parse_value(text: str) -> Any:
    """A Python literal where ``text`` parses as one (``inf`` too), else the stripped text.

    Example:
        >>> parse_value("1.5"), parse_value("(1, 2)"), parse_value("zero"), parse_value("inf")
        (1.5, (1, 2), 'zero', inf)
    """
    text = text.strip()
    if text.lower() in ("inf", "+inf", "infinity", "-inf", "-infinity"):
        return float(text)
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        return text


def parse_setting(text: str) -> tuple[str, Any]:
    """Split ``"KEY=VALUE"`` into the key (dashes read as underscores) and its parsed value.

    Raises:
        ValueError: if ``text`` has no ``=`` or an empty key.

    Example:
        >>> parse_setting("reset-mechanism=zero"), parse_setting("dt=1000")
        (('reset_mechanism', 'zero'), ('dt', 1000))
    """
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ValueError(f"a setting must look like KEY=VALUE, got {text!r}")
    return key.replace("-", "_"), parse_value(value)


def parse_settings(text: str) -> dict[str, Any]:
    """Parse ``"KEY=VALUE,KEY=VALUE,..."`` (an empty text gives no settings).

    Raises:
        ValueError: if an item is not ``KEY=VALUE``.

    Example:
        >>> parse_settings("weight=1.5, factor=(1, 2),reset_mechanism=zero")
        {'weight': 1.5, 'factor': (1, 2), 'reset_mechanism': 'zero'}
    """
    return dict(parse_setting(item) for item in filter(None, _SETTING_SPLIT.split(text.strip())))


def parse_factor(text: str) -> int | tuple[int, int]:
    """Read a factor written ``F`` or ``FX,FY`` (``FXxFY`` too, as :func:`format_factor` writes).

    Only the syntax is checked here; :func:`evdown_torch.checks.check_factor` checks values.

    Raises:
        ValueError: if ``text`` is not one or two integers.

    Example:
        >>> parse_factor("4"), parse_factor("4,2"), parse_factor("4x2")
        (4, (4, 2), (4, 2))
    """
    parts = re.split(r"\s*[,x]\s*", text.strip())
    try:
        values = [int(p) for p in parts]
    except ValueError:
        raise ValueError(f"factor must be F or FX,FY integers, got {text!r}") from None
    if len(values) == 1:
        return values[0]
    if len(values) == 2:
        return values[0], values[1]
    raise ValueError(f"factor must be F or FX,FY integers, got {text!r}")


def format_factor(factor: int | tuple[int, int] | list[int]) -> str:
    """Write a factor as ``"F"`` (same both ways) or ``"FXxFY"``.

    Example:
        >>> format_factor(4), format_factor((2, 2)), format_factor((4, 2))
        ('4', '2', '4x2')
    """
    if isinstance(factor, int):
        return str(factor)
    fx, fy = factor
    return str(fx) if fx == fy else f"{fx}x{fy}"
