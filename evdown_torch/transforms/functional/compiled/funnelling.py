"""Event funnelling's compiled loop: downsample and drop repeats in one pass over the events.

An event repeats an earlier one when both have the same ``(x', y', p)`` and the same ``t``:
in time order, each key remembers the start of the run of equal timestamps it was last kept
in, and an event whose key was kept in the current run is dropped. The same events as the
eager kernel (:mod:`..funnelling`), which lines repeats up with a sort of the keys instead.
"""

from __future__ import annotations

import numpy as np
import torch

from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import (
    columns_of,
    outside_error,
    power_of_two_shifts,
    region_tables,
    region_xy,
)
from evdown_torch.transforms.functional.compiled.scratch import scratch_column

__all__ = ["DENSE_KEYS", "funnelling_batch", "funnelling_sorted"]

#: Keys a call may hold in its dense table of run starts (8 MiB), or 16 per event if more:
#: past that (output grids of many millions of regions) the eager kernel's sort of the keys
#: costs less than clearing the table.
DENSE_KEYS = 1 << 20


@compiled_loop
def _funnel_loop(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, column: np.ndarray,
    row: np.ndarray, shift_x: int, shift_y: int, out_w: int, ends: np.ndarray,
    kept_in: np.ndarray, out_index: np.ndarray, out_x: np.ndarray, out_y: np.ndarray,
    out_t: np.ndarray, out_p: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Keep each time-sorted event whose key was not kept in its run.

    The key is ``(ry * out_w + rx) * 2 + p`` with ``(rx, ry)`` the shifts ``(x >> shift_x,
    y >> shift_y)`` (factors that are powers of two) or, with negative shifts, the tables
    ``(column[x], row[y])``; a run is a stretch of equal ``t`` inside one recording (of
    ``ends``); ``kept_in[key]`` is the start of the run where the key was last kept (-1:
    never). An empty ``out_index`` takes no indices.

    Returns:
        The number ``k`` of kept events, whose index (unless ``out_index`` is empty), region,
        ``t`` and ``p`` are written at ``0 .. k-1``;
        ``-1 - i`` for an event ``i`` outside the tables.
    """
    # Measured on live chunks of the replay (about 20 % of the loop, at factors 1 and 4): the
    # shifts instead of the tables, and no index written where the caller drops it; the last
    # time and the recording's end held in locals, not read again from ``t`` (``t[i - 1]``, a
    # signed index Numba wraps) and ``ends`` each event: 5 % of the loop on captured chunks.
    width = column.shape[0]
    height = row.shape[0]
    indexed = out_index.shape[0] > 0
    n = x.shape[0]
    k = 0
    run = 0
    recording = 0
    end = ends[0]
    previous = t[0] if n else 0
    for i in range(n):
        ti = t[i]
        if ti != previous:  # (at i = 0 it is not: run is already 0)
            run = i
            previous = ti
        while end <= i:  # a recording starts a run of its own
            recording += 1
            end = ends[recording]
            run = i
        xi = x[i]
        yi = y[i]
        if xi < 0 or xi >= width or yi < 0 or yi >= height:
            return -1 - i
        rx, ry = region_xy(xi, yi, shift_x, shift_y, column, row)
        pi = p[i]
        key = (ry * out_w + rx) * 2 + (1 if pi else 0)
        # Every event is written at k, and k moves on past a kept one only: no branch on the
        # key's test, which no predictor guesses (4 to 30 % of the loop on a live chunk).
        kept = kept_in[key] != run
        kept_in[key] = run
        if indexed:
            out_index[k] = i
        out_x[k] = rx
        out_y[k] = ry
        out_t[k] = ti
        out_p[k] = pi
        k += kept
    return k


def _funnel(
    events: Events, factor: tuple[int, int], size: tuple[int, int], ends: np.ndarray,
    seen: Events | None = None, *, indexed: bool,
) -> tuple[Events, np.ndarray]:
    """The loop over ``N >= 1`` time-sorted events on the grid ``size`` of output regions.

    Returns:
        The kept events, and their positions in ``events`` (ascending; empty unless
        ``indexed``).
    """
    width, height = size
    column, row = region_tables(factor, width, height)
    shift_x, shift_y = power_of_two_shifts(factor)
    kept_in = np.full(2 * width * height, -1, dtype=np.int64)
    if seen is not None and seen.num_events and bool(events.t[0] <= seen.t[-1]):
        # The first run shares seen's timestamp: seen's keys count as kept in it.
        keys = (seen.y * (2 * width) + seen.x * 2 + seen.p).numpy()
        kept_in[keys[(keys >= 0) & (keys < kept_in.shape[0])]] = 0
    x, y, t, p = columns_of(events.x, events.y, events.t, events.p)
    n = x.shape[0]
    out_index = (scratch_column("funnelling index", n, np.int64) if indexed
                 else np.empty(0, dtype=np.int64))
    out_x, out_y = (scratch_column(f"funnelling {name}", n, np.int64) for name in ("x", "y"))
    out_t = scratch_column("funnelling t", n, t.dtype)
    out_p = scratch_column("funnelling p", n, p.dtype)
    k = _funnel_loop(x, y, t, p, column, row, shift_x, shift_y, width, ends, kept_in, out_index,
                     out_x, out_y, out_t, out_p)
    if k < 0:
        raise outside_error(-1 - k, x, y, column, row)
    out = Events(*(torch.from_numpy(column[:k]) for column in (out_x, out_y, out_t, out_p)))
    return out, out_index[:k]


def _dense(size: tuple[int, int], n: int) -> bool:
    """Whether a table of the keys of the grid ``size`` fits a call of ``n`` events."""
    return 2 * size[0] * size[1] <= max(DENSE_KEYS, 16 * n)


def funnelling_sorted(
    events: Events, factor: tuple[int, int], *, seen: Events | None, size: tuple[int, int]
) -> Events | None:
    """:func:`~..funnelling.funnelling_sorted` of ``N >= 1`` events on the CPU (the same events).

    ``size``: the output grid every coordinate lies in (:func:`~..funnelling.key_grid`).
    ``None`` for a grid too large for the table (:data:`DENSE_KEYS`).
    """
    n = events.num_events
    if not _dense(size, n):
        return None
    return _funnel(events, factor, size, np.array([n], dtype=np.int64), seen, indexed=False)[0]


def funnelling_batch(
    events: Events, lengths: tuple[int, ...], factor: tuple[int, int], size: tuple[int, int]
) -> tuple[Events, tuple[int, ...]] | None:
    """:func:`~..funnelling.funnelling_batch` of ``N >= 1`` events on the CPU (the same events).

    ``None`` for a grid too large for the table (:data:`DENSE_KEYS`).
    """
    if not _dense(size, events.num_events):
        return None
    ends = np.cumsum(lengths, dtype=np.int64)
    out, kept = _funnel(events, factor, size, ends, indexed=True)
    counts = np.diff(np.searchsorted(kept, ends), prepend=0)
    return out, tuple(counts.tolist())
