"""What the compiled loops share: region tables, the pixel check, the crossings' columns.

The loops that emit level crossings (EventCount's, PhotocurrentPooling's) write them into
:func:`crossing_columns`, grown by :func:`grown_columns`, returned by :func:`crossing_tensors`.

A loop finds an event's region by two table lookups (``column[x]``, ``row[y]``) instead of
two integer divisions per event, or by two shifts where both factors are powers of two
(:func:`region_xy`), and checks the pixel against the tables' extent, so a coordinate outside
the sensor is an error (:func:`outside_error`), never a read out of bounds.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from evdown_torch.transforms.functional.compiled._numba import inlined_helper
from evdown_torch.transforms.functional.compiled.scratch import scratch_column, scratch_copy

__all__ = ["columns_of", "crossing_columns", "crossing_tensors", "grown_columns", "outside_error",
           "power_of_two_shifts", "region_tables", "region_xy"]


@functools.lru_cache(maxsize=64)
def region_tables(factor: tuple[int, int], out_w: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """The lookup tables of region columns and rows (int64; shared, never written).

    ``(column, row)``: ``x // fx`` for each of ``out_w * fx`` values of ``x``, ``y // fy``
    for each of ``rows * fy`` values of ``y``.

    Example:
        >>> column, row = region_tables((2, 3), 2, 2)
        >>> column.tolist(), row.tolist()
        ([0, 0, 1, 1], [0, 0, 0, 1, 1, 1])
    """
    fx, fy = factor
    return np.arange(out_w * fx, dtype=np.int64) // fx, np.arange(rows * fy, dtype=np.int64) // fy


def power_of_two_shifts(factor: tuple[int, int]) -> tuple[int, int]:
    """``(log2 fx, log2 fy)`` when both factors are powers of two, else ``(-1, -1)``.

    A loop finds the region of such factors by two shifts, cheaper still than the tables.

    Example:
        >>> power_of_two_shifts((4, 1)), power_of_two_shifts((4, 3))
        ((2, 0), (-1, -1))
    """
    fx, fy = factor
    if fx & (fx - 1) or fy & (fy - 1):
        return -1, -1
    return fx.bit_length() - 1, fy.bit_length() - 1


@inlined_helper
def region_xy(x: int, y: int, shift_x: int, shift_y: int, column: np.ndarray,
              row: np.ndarray) -> tuple[int, int]:  # pragma: no cover - compiled
    """The region ``(column, row)`` of a pixel ``(x, y)`` inside the tables, in a loop.

    By two shifts where both factors are powers of two (``shift_x >= 0``,
    :func:`power_of_two_shifts`: cheaper than the lookups), else by the tables of
    :func:`region_tables`.
    """
    if shift_x >= 0:
        return x >> shift_x, y >> shift_y
    return column[x], row[y]


def columns_of(*columns: Tensor) -> tuple[np.ndarray, ...]:
    """CPU tensors as contiguous NumPy arrays sharing their memory (the loops' one layout)."""
    return tuple(np.ascontiguousarray(column.numpy()) for column in columns)


def outside_error(
    index: int, x: np.ndarray, y: np.ndarray, column: np.ndarray, row: np.ndarray
) -> ValueError:
    """The error for event ``index``, whose pixel lies outside the loop's tables."""
    return ValueError(
        f"event {index} at (x={int(x[index])}, y={int(y[index])}) lies outside the sensor "
        f"of {len(column)} x {len(row)} pixels"
    )


def crossing_columns(capacity: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Output columns ``(x, y, source event, on)`` for ``capacity`` crossings, uninitialised.

    This thread's scratch columns (:func:`~.scratch.scratch_column`), often the last call's.
    """
    return (scratch_column("crossing x", capacity, np.int64),
            scratch_column("crossing y", capacity, np.int64),
            scratch_column("crossing source", capacity, np.int64),
            scratch_column("crossing on", capacity, np.bool_))


def grown_columns(
    out: tuple[np.ndarray, ...], k: int, capacity: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``out``'s first ``k`` crossings in new columns of ``capacity`` crossings."""
    grown = crossing_columns(capacity)
    for old, new in zip(out, grown, strict=True):
        new[:k] = old[:k]
    return grown


def crossing_tensors(
    out: tuple[np.ndarray, ...], k: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The first ``k`` crossings of ``out`` as tensors ``(x, y, source event, on)``.

    Views of the columns, or copies where most of them is empty (so that the caller does not
    keep the mostly empty columns alive), in this thread's scratch columns
    (:func:`~.scratch.scratch_column`).
    """
    if k < out[0].shape[0] // 2:
        out = tuple(scratch_copy(f"crossing {name} copy", column[:k])
                    for name, column in zip(("x", "y", "source", "on"), out, strict=True))
    x, y, source, on = (torch.from_numpy(column[:k]) for column in out)
    return x, y, source, on
