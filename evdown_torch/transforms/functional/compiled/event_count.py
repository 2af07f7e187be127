"""EventCount's compiled loop: each event in time order, its region's sum and reference rule.

The same arithmetic as the eager kernel (:mod:`..event_count`): the threshold is the
rational ``a / b`` of :func:`~..reference.threshold_fraction` (capped as
:func:`~..reference.capped_threshold` caps it), and after each event its region's
``b * S`` (``S`` the integer sum of the region's pixel levels) is compared with the levels
``a * n_r * j`` in int64, so both paths give the same events, bit for bit.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from evdown_torch._regions import region_pixel_count
from evdown_torch.checks import check_output_count, output_limit
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import (
    columns_of,
    crossing_columns,
    crossing_tensors,
    grown_columns,
    outside_error,
    power_of_two_shifts,
    region_tables,
    region_xy,
)
from evdown_torch.transforms.functional.compiled.scratch import scratch_column
from evdown_torch.transforms.functional.reference import capped_threshold, threshold_fraction
from evdown_torch.transforms.functional.settings import ThresholdSettings

__all__ = ["event_count_batch", "event_count_step"]


@compiled_loop
def _event_count_loop(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, column: np.ndarray, row: np.ndarray,
    shift_x: int, shift_y: int, out_w: int, ends: np.ndarray, block: int,
    level_step: np.ndarray, b: int, level_sum: np.ndarray, reference: np.ndarray, start: int,
    k: int, most: int, out_x: np.ndarray, out_y: np.ndarray, out_source: np.ndarray,
    out_on: np.ndarray, count_only: bool,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """The reference rule after each event ``start, start + 1, ...`` (time-sorted).

    Region of event ``i``: ``rec * block + ry * out_w + rx`` with ``(rx, ry)`` the shifts
    ``(x >> shift_x, y >> shift_y)`` (factors that are powers of two) or, with negative
    shifts, the tables ``(column[x], row[y])``; ``rec`` is the recording whose span ``ends``
    (each recording's end, the last ``N``) holds ``i``. Writes each crossing's region
    ``(rx, ry)``, source event and polarity at ``k, k + 1, ...``; stops before an event that
    could overflow the outputs (``most`` crossings at most per event). ``count_only``: counts
    the crossings, writes nothing, never stops.

    Returns:
        ``(next event, crossings so far)``; ``(-1 - i, k)`` for an event ``i`` outside the
        tables (a coordinate outside the sensor).
    """
    # Three measured choices: the event index is unsigned (``_numba``, "Unsigned indices"),
    # and each region's next crossing levels ``(q + 1) * step`` and ``(q - 1) * step`` are
    # kept (one comparison pair per event, no product): about 15 % of the loop on a 1M-event
    # stream; a region's sum, levels and reference lie in one row of ``state`` (one cache
    # line an event, not one per column): 0.70 against 0.96 ms on live chunks of the replay
    # (1,024 regions). ``level_sum`` and ``reference`` take the rows' values back at every
    # return.
    n = x.shape[0]
    capacity = out_source.shape[0]
    width = column.shape[0]
    height = row.shape[0]
    regions = level_sum.shape[0]
    state = np.empty((regions, 4), np.int64)  # sum, high, low, reference
    for r in range(regions):
        q = reference[r]
        state[r, 0], state[r, 1] = level_sum[r], (q + 1) * level_step[r]
        state[r, 2], state[r, 3] = (q - 1) * level_step[r], q
    recording = 0
    i = start
    while i < n:
        while ends[recording] <= i:
            recording += 1
        offset = recording * block
        stop = ends[recording]
        if not count_only:  # events that cannot overflow the outputs: no check inside
            room = (capacity - k) // most
            if room == 0:
                break
            stop = min(stop, i + room)
        for j in range(np.uint64(i), np.uint64(stop)):
            xj = x[j]
            yj = y[j]
            if xj < 0 or xj >= width or yj < 0 or yj >= height:
                stop = -1 - np.int64(j)
                break
            rx, ry = region_xy(xj, yj, shift_x, shift_y, column, row)
            r = np.uint64(offset + ry * out_w + rx)
            s = state[r, 0] + (1 if p[j] else -1)
            state[r, 0] = s
            scaled = s * b
            if scaled >= state[r, 1] or scaled <= state[r, 2]:  # crossings: ON (d = 1) or OFF
                step = level_step[r]
                q = state[r, 3]
                d = 1 if scaled >= state[r, 1] else -1
                while d * scaled >= d * (q + d) * step:
                    q += d
                    if not count_only:
                        out_x[k] = rx
                        out_y[k] = ry
                        out_source[k] = j
                        out_on[k] = d > 0
                    k += 1
                state[r, 1], state[r, 2], state[r, 3] = (q + 1) * step, (q - 1) * step, q
        i = stop
        if i < 0:  # an event outside the tables
            break
    for r in range(regions):
        level_sum[r], reference[r] = state[r, 0], state[r, 3]
    return i, k


@functools.lru_cache(maxsize=32)
def _level_steps(
    sensor_size: tuple[int, int, int], factor: tuple[int, int], regions: int, a: int
) -> np.ndarray:
    """``a * n_r`` of each of ``regions`` regions (int64; shared between calls, never written)."""
    return region_pixel_count(torch.arange(regions), sensor_size, factor).numpy() * a


def _run(
    events: Events, state: tuple[Tensor, Tensor], settings: ThresholdSettings,
    lengths: tuple[int, ...] | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, tuple[Tensor, Tensor]]:
    """The loop over ``N >= 1`` time-sorted events.

    ``state``: ``(level_sum, reference)``, EventCount's state. ``lengths``: a batch's
    recordings, each in its own coordinates; ``None``: one stream (stacked recordings
    included).

    Returns:
        ``(x, y, source event, on)`` of each output event and the new ``(level_sum,
        reference)`` (new tensors: ``state`` is left as it was, also when the output limit is
        exceeded).
    """
    old_sum, old_reference = state
    n = events.num_events
    bound = int(old_sum.abs().max()) + n if old_sum.numel() else n
    fraction = capped_threshold(threshold_fraction(settings.threshold), bound)
    a, b = fraction.numerator, fraction.denominator
    out_w, out_h, _ = settings.output_sensor_size
    regions = old_sum.shape[0]
    if lengths is None:
        ends, block, rows = np.array([n], dtype=np.int64), 0, regions // out_w
    else:
        ends, block, rows = np.cumsum(lengths, dtype=np.int64), out_w * out_h, out_h
    column, row = region_tables(settings.factor, out_w, rows)
    shift_x, shift_y = power_of_two_shifts(settings.factor)
    level_step = _level_steps(settings.sensor_size, settings.factor, regions, a)
    # An event moves b * S by b: it crosses at most b // (a * n_r) + 1 levels.
    most = b // int(level_step.min()) + 1
    room = output_limit()  # events this call may emit
    capacity = min(n * most, 2 * n + most)
    if room is not None:
        capacity = min(capacity, room + most)
    level_sum, reference = old_sum.clone(), old_reference.clone()
    x, y, p = columns_of(events.x, events.y, events.p)
    sums, levels = level_sum.numpy(), reference.numpy()
    out = crossing_columns(capacity)
    i, k = 0, 0
    while True:
        i, k = _event_count_loop(x, y, p, column, row, shift_x, shift_y, out_w, ends, block,
                                 level_step, b, sums, levels, i, k, most, *out, False)
        if i < 0:
            raise outside_error(-1 - i, x, y, column, row)
        if room is not None and k > room:  # count the rest, for the error's message
            _, total = _event_count_loop(x, y, p, column, row, shift_x, shift_y, out_w, ends,
                                         block, level_step, b, sums, levels, i, k, most, *out,
                                         True)
            check_output_count(total)
        if i == n:
            break
        capacity = 2 * capacity if room is None else min(2 * capacity, room + most)
        out = grown_columns(out, k, capacity)
    out_x, out_y, source, on = crossing_tensors(out, k)
    return out_x, out_y, source, on, (level_sum, reference)


def _taken(t: Tensor, source: Tensor) -> Tensor:
    """``t[source]`` in a scratch column (:func:`~.scratch.scratch_column`)."""
    values = t.numpy()
    out = scratch_column("event count t", source.shape[0], values.dtype)
    np.take(values, source.numpy(), out=out, mode="clip")  # (in range: "raise" buffers)
    return torch.from_numpy(out)


def event_count_step(
    events: Events, state: tuple[Tensor, Tensor], settings: ThresholdSettings
) -> tuple[Events, tuple[Tensor, Tensor]]:
    """``event_count_step`` on the CPU: the same events and ``(level_sum, reference)``."""
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device), state
    x, y, source, on, new_state = _run(events, state, settings, None)
    return Events(x, y, _taken(events.t, source), on), new_state


def event_count_batch(
    events: Events, lengths: tuple[int, ...], settings: ThresholdSettings,
    state: tuple[Tensor, Tensor],
) -> tuple[Events, tuple[int, ...]]:
    """``event_count_batch`` on the CPU: the same events and counts (``state``: fresh)."""
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device), tuple(0 for _ in lengths)
    x, y, source, on, _ = _run(events, state, settings, lengths)
    ends = torch.tensor(lengths, dtype=torch.int64).cumsum(0)
    counts = torch.searchsorted(source, ends).diff(prepend=torch.zeros(1, dtype=torch.int64))
    return Events(x, y, events.t.index_select(0, source), on), tuple(counts.tolist())
