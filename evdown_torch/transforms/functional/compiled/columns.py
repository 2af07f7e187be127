"""Tonic structured arrays read and written in one compiled pass: the conversions at the edge.

:func:`~evdown_torch.events.to_events` copies each field of a structured array with NumPy (a
cast and a copy per field), then checks the coordinates' ranges and the polarity's values with
torch, and :func:`~evdown_torch.events.from_events` writes each field back: about ten passes
over the events. On the CPU in the live replay (a Tonic array of 184,000 events every 10 ms)
they took about 2.4 ms of Downsample's 3.8 ms per chunk, more than the method's own loop
(docs/benchmarks.md, "Fourth session of 2026-12-02"). Here one loop reads the four fields
(strided views of the array, no copy), writes the kernels' columns and gathers the facts the
checks need, and one loop writes a result's columns into the fields; the checks themselves
(and their errors) stay in :mod:`evdown_torch.events`. The values are NumPy's: each field is
converted as NumPy's unsafe cast converts it (``astype``), so both paths give the same
columns and arrays, bit for bit (tested on every supported field dtype).

Numba reads native-endian fields of integer, float32/float64 and bool dtypes
(:func:`compiled_fields`); an array with any other field takes the NumPy path.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.scratch import scratch_column

__all__ = ["ColumnFacts", "compiled_fields", "read_columns", "write_columns"]

#: Field dtypes the loops read and write: ``np.dtype.kind`` and item sizes.
_KINDS = {"b": (1,), "i": (1, 2, 4, 8), "u": (1, 2, 4, 8), "f": (4, 8)}


@functools.lru_cache(maxsize=64)  # (asked at every call; a stream's chunks share a dtype)
def compiled_fields(dtype: np.dtype) -> bool:
    """Whether every field of a structured ``dtype`` is one the loops take.

    Native byte order, and integer, float32/float64 or bool.

    Example:
        >>> compiled_fields(np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")]))
        True
        >>> compiled_fields(np.dtype([("x", ">i2"), ("y", "<i2"), ("t", "<f2"), ("p", "?")]))
        False
    """
    for name in dtype.names or ():
        field = dtype.fields[name][0]  # type: ignore[index]
        if not field.isnative or field.itemsize not in _KINDS.get(field.kind, ()):
            return False
    return True


class ColumnFacts(NamedTuple):
    """What :func:`read_columns` learnt of the events while reading them.

    Attributes:
        x_range: ``(min, max)`` of ``x`` as int64 (``(0, -1)`` without events).
        y_range: ``(min, max)`` of ``y``.
        t_finite: every ``t`` is finite (always so for integer ``t``).
        t_sorted: ``t`` is non-decreasing (in stable time order already).
        p_negative: some ``p`` is negative (numeric ``p``).
        p_binary: every ``p`` is 0 or 1 (numeric ``p``).
        p_signed: every ``p`` is -1 or +1 (numeric ``p``).
    """

    x_range: tuple[int, int]
    y_range: tuple[int, int]
    t_finite: bool
    t_sorted: bool
    p_negative: bool
    p_binary: bool
    p_signed: bool


@compiled_loop
def _read_loop(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, numeric_p: bool,
    out_x: np.ndarray, out_y: np.ndarray, out_t: np.ndarray, out_p: np.ndarray,
) -> tuple[int, int, int, int, bool, bool, bool, bool, bool]:  # pragma: no cover
    """Each field cast to its column's dtype (as ``astype``); the :class:`ColumnFacts`.

    The facts are counted in separate passes over the columns written (no flag carried from
    event to event), which measured about 15 % faster on a 1M-event array than one pass.
    """
    n = x.shape[0]
    x_lo, x_hi, y_lo, y_hi = 0, -1, 0, -1
    if n:
        x_lo, x_hi, y_lo, y_hi = np.int64(x[0]), np.int64(x[0]), np.int64(y[0]), np.int64(y[0])
    for i in range(n):
        out_x[i] = x[i]
        out_y[i] = y[i]
        out_t[i] = t[i]
        xi, yi = out_x[i], out_y[i]
        x_lo, x_hi = min(x_lo, xi), max(x_hi, xi)
        y_lo, y_hi = min(y_lo, yi), max(y_hi, yi)
    not_finite = 0
    for i in range(n):
        not_finite += not np.isfinite(out_t[i])
    unordered = 0
    for i in range(1, n):
        unordered += not out_t[i] >= out_t[i - 1]
    negative, not_binary, not_signed = 0, 0, 0
    if numeric_p:
        for i in range(n):
            pi = p[i]
            negative += pi < 0
            # ``&``, not ``or``: a short-circuit is a branch an event on a polarity that
            # alternates at random (2.4x slower on 250,000 int8 polarities)
            not_binary += (pi != 0) & (pi != 1)
            not_signed += (pi != 1) & (pi != -1)
            out_p[i] = pi > 0
    else:
        for i in range(n):
            out_p[i] = p[i]
    return (x_lo, x_hi, y_lo, y_hi, not_finite == 0, unordered == 0, negative > 0,
            not_binary == 0, not_signed == 0)


def read_columns(
    data: np.ndarray, t_dtype: type[np.integer] | type[np.floating]
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], ColumnFacts]:
    """A structured array's fields as the kernels' columns, in one pass.

    Args:
        data: ``(N,)`` structured array with fields ``x``, ``y``, ``t``, ``p`` of dtypes
            :func:`compiled_fields` accepts (others are not read).
        t_dtype: ``np.int64`` or ``np.float64``, the timestamps' column dtype.

    Returns:
        ``((x, y, t, p), facts)``: int64 ``x`` and ``y``, ``t`` of ``t_dtype`` and bool
        ``p`` (``p > 0`` for a numeric field), each equal to NumPy's ``astype`` of the field,
        in this thread's scratch columns (:func:`~.scratch.scratch_column`: memory no
        other object refers to, often the last call's); the :class:`ColumnFacts`.
    """
    n = data.shape[0]
    columns = (scratch_column("read x", n, np.int64), scratch_column("read y", n, np.int64),
               scratch_column("read t", n, t_dtype), scratch_column("read p", n, np.bool_))
    p = data["p"]
    facts = _read_loop(data["x"], data["y"], data["t"], p, p.dtype != np.bool_, *columns)
    x_lo, x_hi, y_lo, y_hi, *flags = facts
    return columns, ColumnFacts((int(x_lo), int(x_hi)), (int(y_lo), int(y_hi)),
                                *(bool(flag) for flag in flags))


@compiled_loop
def _write_loop(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, polarity: int,
    out_x: np.ndarray, out_y: np.ndarray, out_t: np.ndarray, out_p: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Each column cast into its field (as NumPy assigns); ``polarity``: :func:`write_columns`."""
    for i in range(x.shape[0]):
        out_x[i] = x[i]
        out_y[i] = y[i]
        out_t[i] = t[i]
        if polarity == 0:
            out_p[i] = p[i]
        elif p[i]:
            out_p[i] = 1
        else:
            out_p[i] = 0 if polarity == 1 else -1


def write_columns(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, polarity: int, out: np.ndarray
) -> None:
    """Write the columns of a result into the fields of ``out``, in one pass.

    Args:
        x: ``(N,)`` int64.
        y: ``(N,)`` int64.
        t: ``(N,)`` int64 or float64.
        p: ``(N,)`` bool.
        polarity: the field's encoding: 0 as bool, 1 as 0/1, 2 as -1/+1.
        out: ``(N,)`` structured array of a dtype :func:`compiled_fields` accepts.
    """
    _write_loop(x, y, t, p, polarity, out["x"], out["y"], out["t"], out["p"])
