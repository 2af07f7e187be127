"""Downsample's compiled loop: each event's region, by two shifts or two table lookups."""

from __future__ import annotations

import numpy as np
import torch

from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import (
    columns_of,
    power_of_two_shifts,
    region_tables,
)
from evdown_torch.transforms.functional.compiled.scratch import scratch_column, scratch_copy
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = ["downsample_step"]


@compiled_loop
def _downsample_loop(
    x: np.ndarray, y: np.ndarray, fx: int, fy: int, column: np.ndarray, row: np.ndarray,
    shift_x: int, shift_y: int, out_x: np.ndarray, out_y: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out_x = x // fx``, ``out_y = y // fy`` (floored).

    By the shifts ``x >> shift_x``, ``y >> shift_y`` for factors that are powers of two (an
    arithmetic shift floors every coordinate, inside the sensor or not; a loop without a
    branch, which LLVM vectorises: a third of the tables' time on a live chunk); else
    (negative shifts) by the tables where they reach, and a division beyond them.
    """
    if shift_x >= 0:
        for i in range(x.shape[0]):
            out_x[i] = x[i] >> shift_x
            out_y[i] = y[i] >> shift_y
        return
    width = column.shape[0]
    height = row.shape[0]
    for i in range(x.shape[0]):
        xi = x[i]
        yi = y[i]
        out_x[i] = column[xi] if 0 <= xi < width else xi // fx
        out_y[i] = row[yi] if 0 <= yi < height else yi // fy


def downsample_step(events: Events, settings: RegionSettings) -> Events:
    """:func:`~..downsample.downsample_step` on the CPU: the same events (new tensors).

    Any coordinates (a batch's stacked rows too): beyond the sensor, a division. The
    output's columns are this thread's scratch columns (:func:`~.scratch.scratch_column`):
    memory that no other object refers to, the last call's where the caller let it go.
    """
    out_w, out_h, _ = settings.output_sensor_size
    fx, fy = settings.factor
    column, row = region_tables(settings.factor, out_w, out_h)
    shift_x, shift_y = power_of_two_shifts(settings.factor)
    x, y, t, p = columns_of(events.x, events.y, events.t, events.p)
    n = x.shape[0]
    out_x = scratch_column("downsample x", n, x.dtype)
    out_y = scratch_column("downsample y", n, y.dtype)
    _downsample_loop(x, y, fx, fy, column, row, shift_x, shift_y, out_x, out_y)
    out_t, out_p = scratch_copy("downsample t", t), scratch_copy("downsample p", p)
    return Events(torch.from_numpy(out_x), torch.from_numpy(out_y), torch.from_numpy(out_t),
                  torch.from_numpy(out_p))
