"""The bounded-delay window's upkeep in compiled loops: held knots, the merge, the next knots.

A bounded-delay session step (:func:`~..estimation.stream.estimation_step`) finds the chunk's
held knots, merges them with the state's knots and the chunk into a time-sorted window, and
keeps of the window the knots the future needs. In eager torch that upkeep took about 28 ms
of a 10 ms chunk of 184,000 events (sorts by pixel, segmented sums, scatters); here each is
one pass or two over the events, with a pixel's running state in a table.

Each function gives the same tensors as its eager counterpart, bit for bit (same values,
dtypes and order):

* :func:`held_knots`: :func:`~..estimation.delay.held_knots`;
* :func:`merge_by_time`: :func:`~..estimation.delay.merge_by_time`;
* :func:`next_knots`: the step's ``_trim`` of the window (after ``_recent``, which only
  prunes what ``_trim`` drops), sorted stably by time.

A call's pixel table is ``np.empty`` of the largest pixel id, read through a sparse set
(a pixel's slot counts only where the slot's owner is that pixel), so a call costs no
``O(W * H)`` clearing, whatever the sensor. Timestamps are int64, float64 or float32; the
arithmetic on them is in their dtype, as torch's (a delay is rounded to float32 for float32
``t``, as torch rounds a Python scalar). The tensors are CPU tensors.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import columns_of
from evdown_torch.transforms.functional.compiled.scratch import scratch_column
from evdown_torch.transforms.functional.compiled.sorting import merge_order
from evdown_torch.transforms.functional.estimation import delay

__all__ = ["held_knots", "merge_by_time", "next_knots"]

#: Timestamp dtypes the loops take.
TIME_DTYPES = (torch.int64, torch.float64, torch.float32)

#: Runs of equal times up to this length are ordered by insertion sort, longer ones by a
#: stable merge sort.
_SHORT_RUN = 64


@compiled_loop
def _slots(pixel: np.ndarray, bound: int, slot: np.ndarray,
           owner: np.ndarray) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """``(N,)`` int64 slot of each pixel id in ``[0, bound)`` (in order of first appearance).

    ``slot`` and ``owner``: int64 columns of at least ``N`` elements (``slot``'s first ``N``
    are returned; ``owner`` is scratch).

    Returns:
        ``(slot, number of slots)``. The table of ``bound`` entries is not cleared: a slot
        read from it counts only where the slot's owner is the pixel.
    """
    table = np.empty(bound, dtype=np.int64)
    slot = slot[:pixel.shape[0]]
    count = 0
    for i in range(pixel.shape[0]):  # (unsigned indices: ``_numba``, "Unsigned indices")
        p = pixel[i]
        s = table[np.uint64(p)]
        if s < 0 or s >= count or owner[np.uint64(s)] != p:
            s = count
            table[np.uint64(p)] = s
            owner[np.uint64(s)] = p
            count += 1
        slot[i] = s
    return slot, count


@compiled_loop
def _pixel_ids(x: np.ndarray, y: np.ndarray, width: int,
               pixel: np.ndarray) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """``(N,)`` int64 pixel id ``y * width + x`` of each event, and one past the largest.

    Written into the first ``N`` elements of the int64 column ``pixel``. The bound is -1
    where an id is negative (a negative coordinate, or an overflow).
    """
    pixel = pixel[:x.shape[0]]
    bound = 0
    for i in range(x.shape[0]):
        pixel[i] = y[i] * width + x[i]
        if pixel[i] < 0:
            return pixel, -1
        bound = max(bound, pixel[i] + 1)
    return pixel, bound


@compiled_loop
def _order_ties(t: np.ndarray, key: np.ndarray, order: np.ndarray,
                keys: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """``(M,)`` int64 stable order by ``key`` inside each run of equal ``t`` (``t`` ascending).

    ``order`` and ``keys``: int64 columns of at least ``M`` elements (``order``'s first
    ``M`` are returned; ``keys`` is scratch).
    """
    n = t.shape[0]
    order = order[:n]
    keys = keys[:n]  # keys[j] = key[order[j]] in the run being sorted
    start = 0
    while start < n:
        end = start + 1
        while end < n and t[end] == t[start]:
            end += 1
        if end - start <= _SHORT_RUN:  # insertion sort: stable
            for j in range(start, end):
                moved = key[j]
                k = j
                while k > start and keys[k - 1] > moved:
                    keys[k] = keys[k - 1]
                    order[k] = order[k - 1]
                    k -= 1
                keys[k] = moved
                order[k] = j
        else:  # (a loop, not a slice assignment: see _grown in .estimation)
            run = merge_order(key[start:end])
            for j in range(end - start):
                order[start + j] = start + run[j]
        start = end
    return order


@compiled_loop
def _held_loop(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, t_start: np.ndarray, delay: np.generic,
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The held knots of ``N >= 1`` events, in :func:`held_knots`' order.

    A knot is held before an event more than ``delay`` after its pixel's previous event in
    the input's order (``t_start[i]``, or ``t_start[0]`` for all, before the pixel's first
    event ``i``), at the event's time less ``delay``.

    Returns:
        ``(status, x, y, t)`` of the held knots: status 0, or -1 for a negative coordinate
        or pixel id.
    """
    n = t.shape[0]
    per_event = t_start.shape[0] == n
    width = np.int64(0)  # (not a literal 0: one compile of _pixel_ids, not two)
    for i in range(n):
        if x[i] < 0 or y[i] < 0:
            return -1, np.empty(0, np.int64), np.empty(0, np.int64), t[:0].copy()
        width = max(width, x[i] + 1)
    pixel, bound = _pixel_ids(x, y, width, np.empty(n, np.int64))
    if bound < 0:  # (overflow)
        return -1, np.empty(0, np.int64), np.empty(0, np.int64), t[:0].copy()
    slot, count = _slots(pixel, bound, np.empty(n, np.int64), np.empty(n, np.int64))
    last = np.empty(count, dtype=t.dtype)
    seen = np.zeros(count, dtype=np.bool_)
    at = np.empty(n, dtype=np.int64)
    held_t = np.empty_like(t)
    m = 0
    sorted_t = True
    for i in range(n):
        s = np.uint64(slot[i])  # (unsigned: ``_numba``, "Unsigned indices")
        previous = last[s] if seen[s] else t_start[i if per_event else 0]
        seen[s] = True
        last[s] = t[i]
        if t[i] - previous > delay:
            held_t[m] = t[i] - delay
            at[m] = i
            if m and held_t[m] < held_t[m - 1]:
                sorted_t = False
            m += 1
    held_t, at = held_t[:m], at[:m]
    key = pixel[at]
    if sorted_t:  # time-sorted events: ties (equal held times) ordered by pixel
        order = _order_ties(held_t, key, np.empty(m, np.int64), np.empty(m, np.int64))
    else:  # a stable sort by pixel, then by held time
        by_pixel = merge_order(key)
        order = by_pixel[merge_order(held_t[by_pixel])]
    out_x = np.empty(m, dtype=np.int64)
    out_y = np.empty(m, dtype=np.int64)
    out_t = np.empty_like(held_t)
    for j in range(m):
        i = at[order[j]]
        out_x[j] = x[i]
        out_y[j] = y[i]
        out_t[j] = held_t[order[j]]
    return 0, out_x, out_y, out_t


@compiled_loop
def _next_loop(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, change: np.ndarray, before: np.generic,
    keep: int, width: int, work: tuple[np.ndarray, ...], kept: np.ndarray,
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """The knots :func:`next_knots` keeps of ``N >= 1`` time-sorted events.

    A backward pass over the events earlier than ``before`` counts each pixel's knot times
    from its last, so that each event knows whether its knot is among its pixel's last
    ``keep``; a forward pass adds up each pixel's changes since its last kept knot and, at
    the end of each run of equal times, emits the kept knots of the run's pixels.

    Returns:
        ``(status, x, y, t, p, change)`` of the kept knots in order of time, then pixel
        (``x``, ``y`` of the pixel id, ``p`` = ``change > 0``): status 0, or -1 for a
        negative pixel id. ``work``: eight int64 columns and ``kept`` a bool one, each of at
        least ``N`` elements, for the loop's own columns (the caller's scratch columns,
        :mod:`.scratch`); the knots returned are new arrays.
    """
    n = t.shape[0]
    pixel, bound = _pixel_ids(x, y, width, work[0])
    if bound < 0:
        none = np.empty(0, np.int64)
        return -1, none, none, t[:0].copy(), np.empty(0, np.bool_), none
    slot, count = _slots(pixel, bound, work[1], work[2])
    cut = np.searchsorted(t, before)  # events before it: t < before
    knots = np.zeros(count, dtype=np.int64)  # a pixel's knot times before cut, from its last
    current = np.empty(count, dtype=t.dtype)
    kept = kept[:cut]
    # (Indices are cast to unsigned: ``_numba``, "Unsigned indices".)
    for back in range(np.uint64(cut)):
        i = np.uint64(cut) - np.uint64(1) - back
        s = np.uint64(slot[i])
        if knots[s] == 0 or t[i] != current[s]:
            knots[s] += 1
            current[s] = t[i]
        kept[i] = knots[s] <= keep
    pending = np.zeros(count, dtype=np.int64)  # changes since the pixel's last kept knot
    last = np.empty(count, dtype=np.int64)  # the pixel's last event in this run of times
    run_of = np.full(count, -1, dtype=np.int64)
    touched, out_at, out_change = work[3], work[4], work[5]
    m = 0
    start = 0
    k = 0
    for i in range(n + 1):
        if i == n or t[i] != t[np.uint64(start)]:  # the run [start, i) of equal times ends
            for j in range(k):
                s = np.uint64(touched[j])
                e = last[s]
                if e >= cut or kept[np.uint64(e)]:
                    out_at[m] = e
                    out_change[m] = pending[s]
                    pending[s] = 0
                    m += 1
            if i == n:
                break
            start = i
            k = 0
        s = np.uint64(slot[i])
        pending[s] += change[i]
        last[s] = i
        if run_of[s] != start:
            run_of[s] = start
            touched[k] = s
            k += 1
    out_at = out_at[:m]
    order = _order_ties(t[out_at], pixel[out_at], work[6], work[7])
    knot_x = np.empty(m, dtype=np.int64)
    knot_y = np.empty(m, dtype=np.int64)
    knot_t = np.empty(m, dtype=t.dtype)
    knot_p = np.empty(m, dtype=np.bool_)
    knot_change = np.empty(m, dtype=np.int64)
    for j in range(m):
        e = out_at[order[j]]
        knot_y[j] = pixel[e] // width
        knot_x[j] = pixel[e] - knot_y[j] * width
        knot_t[j] = t[e]
        knot_change[j] = out_change[order[j]]
        knot_p[j] = knot_change[j] > 0
    return 0, knot_x, knot_y, knot_t, knot_p, knot_change


@compiled_loop
def _merge_loop(
    ts: tuple[np.ndarray, ...], xs: tuple[np.ndarray, ...], ys: tuple[np.ndarray, ...],
    ps: tuple[np.ndarray, ...], changes: tuple[np.ndarray, ...], p_from_change: bool,
    out_x: np.ndarray, out_y: np.ndarray, out_t: np.ndarray, out_p: np.ndarray,
    out_change: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Merge the time-sorted parts into the outputs, a tie taking the earlier part first.

    The head of the part with the earliest head is copied with the elements after it that
    still come before every other part's head (a run at a time). ``p_from_change``: the
    output polarity is ``change > 0`` instead of the parts' polarity.
    """
    k = len(ts)
    heads = np.zeros(k, dtype=np.int64)
    o = 0
    while o < out_t.shape[0]:
        best = -1
        for j in range(k):
            if heads[j] < ts[j].shape[0] and (best < 0 or ts[j][heads[j]] < ts[best][heads[best]]):
                best = j
        # The run of best's elements before the others' heads: strictly before the heads
        # of earlier parts, not after those of later ones.
        strict, weak = False, False
        below, upto = out_t[o], out_t[o]  # (assigned before read: typed placeholders)
        for j in range(k):
            if j == best or heads[j] >= ts[j].shape[0]:
                continue
            head = ts[j][heads[j]]
            if j < best and (not strict or head < below):
                strict, below = True, head
            elif j > best and (not weak or head < upto):
                weak, upto = True, head
        t, h = ts[best], heads[best]
        x, y, p, change = xs[best], ys[best], ps[best], changes[best]
        while True:  # the head first (also should a NaN compare false with everything)
            out_x[o] = x[h]
            out_y[o] = y[h]
            out_t[o] = t[h]
            out_change[o] = change[h]
            out_p[o] = change[h] > 0 if p_from_change else p[h]
            h += 1
            o += 1
            if h == t.shape[0] or (strict and not t[h] < below) or (weak and not t[h] <= upto):
                break
        heads[best] = h


def _scalar(value: Tensor | float, dtype: torch.dtype) -> np.generic:
    """``value`` as a NumPy scalar of ``dtype`` (rounded once, as torch rounds a scalar)."""
    scalar = value.to(dtype) if isinstance(value, Tensor) else torch.tensor(value, dtype=dtype)
    return scalar.reshape(1).numpy()[0]


def held_knots(events: Events, *, max_delay: float, t_start: Tensor) -> Events:
    """:func:`~..estimation.delay.held_knots` on the CPU: the same knots, in the same order.

    Args:
        events: ``N`` events in stable time order (others are ordered as the eager kernel
            orders them), ``x``, ``y`` non-negative (timestamps other than int64, float64
            and float32 go to the eager kernel).
        max_delay: ``D`` > 0, in the stream's time unit (a whole number for int64 ``t``).
        t_start: ``()`` first timestamp of the stream, or ``(N,)`` one for each event (its
            pixel's last knot before these events); of ``t``'s dtype.

    Returns:
        ``M`` held knots: int64 ``x``, ``y``, ``t`` of the events' dtype, ``p`` False, in
        stable time order, ties in pixel order ``y * (max x + 1) + x``; ``events`` itself
        when ``N == 0``.

    Raises:
        ValueError: for a ``max_delay`` that is not whole with integer ``t``, or a negative
            coordinate.

    Example:
        >>> ev = Events.from_columns([0, 1, 0], [0, 0, 0], [0, 4, 10], [1, 0, 1])
        >>> held = held_knots(ev, max_delay=3, t_start=ev.t[0])
        >>> held.t.tolist(), held.x.tolist()
        ([1, 7], [1, 0])
    """
    d = delay.effective_delay(max_delay, events.t)
    if events.num_events == 0:
        return events
    if events.t.dtype not in TIME_DTYPES:
        return delay.held_knots(events, max_delay=max_delay, t_start=t_start)
    x, y, t, start = columns_of(events.x, events.y, events.t,
                                t_start.to(events.t.dtype).reshape(-1))
    status, out_x, out_y, out_t = _held_loop(x, y, t, start, _scalar(d, events.t.dtype))
    if status < 0:
        raise ValueError("held_knots needs non-negative pixel coordinates")
    return Events(torch.from_numpy(out_x), torch.from_numpy(out_y), torch.from_numpy(out_t),
                  torch.from_numpy(np.zeros(out_t.shape[0], dtype=np.bool_)))


def merge_by_time(parts: list[tuple[Events, Tensor]]) -> tuple[Events, Tensor]:
    """:func:`~..estimation.delay.merge_by_time` on the CPU: the same events and changes.

    Args:
        parts: time-sorted events and their ``(N_i,)`` level changes (any integer dtype),
            each column of one dtype in every part (other parts go to the eager kernel).

    Returns:
        ``(events, change)``: the ``sum(N_i)`` events in stable time order, a tie keeping the
        parts' order; polarity that of the parts below :data:`~..estimation.delay.SMALL_WINDOW`
        events, ``change > 0`` from there on (as the eager kernel's two paths give).

    Example:
        >>> a = Events.from_columns([0, 1], [0, 0], [2, 5], [1, 0])
        >>> b = Events.from_columns([2], [0], [2], [1])
        >>> merged, change = merge_by_time([(a, torch.tensor([1, -1])), (b, torch.tensor([3]))])
        >>> merged.x.tolist(), change.tolist()
        ([0, 2, 1], [1, 3, -1])
    """
    columns = [columns_of(events.t, events.x, events.y, events.p, change)
               for events, change in parts]
    kinds = {tuple(column.dtype for column in part) for part in columns}
    if len(kinds) != 1 or parts[0][0].p.dtype != torch.bool or (
            parts[0][0].t.dtype not in TIME_DTYPES):
        return delay.merge_by_time(parts)  # no parts, dtypes torch promotes, or other dtypes
    ts, xs, ys, ps, changes = (tuple(column) for column in zip(*columns, strict=True))
    total = sum(t.shape[0] for t in ts)
    out = [np.empty(total, dtype=column[0].dtype) for column in (xs, ys, ts, ps, changes)]
    _merge_loop(ts, xs, ys, ps, changes, total >= delay.SMALL_WINDOW, *out)
    x, y, t, p, change = (torch.from_numpy(column) for column in out)
    return Events(x, y, t, p), change


def next_knots(
    window: Events, change: Tensor, *, before: Tensor, keep: int, width: int
) -> tuple[Events, Tensor]:
    """The knot events of a session's next state, kept of its window, in time order.

    Of each pixel's knots (one per pixel and time: the last event of each run), those at or
    after ``before`` and its last ``keep`` ones before ``before``; the first kept knot of a
    pixel carries the pixel's whole level as its change. The same tensors as the step's
    ``_trim(_recent(window, ...), ...)`` sorted stably by time.

    Args:
        window: ``N`` knot events in stable time order (not earlier than the stream's
            ``t_start``), pixel ids ``y * width + x`` non-negative.
        change: ``(N,)`` integer level change of each event.
        before: ``()`` the next horizon, of ``t``'s dtype.
        keep: knots kept before ``before`` per pixel (the method's lag: 1 or 2).
        width: the sensor's width ``W``.

    Returns:
        ``(knots, change)``: the ``K`` kept knots (int64 ``x``, ``y`` of their pixel id,
        ``t`` of the window's dtype, ``p`` = ``change > 0``) in stable time order, ties in
        pixel order, and their ``(K,)`` int64 level changes.

    Raises:
        ValueError: for a negative pixel id.
        TypeError: for timestamps other than int64, float64 and float32.

    Example:
        >>> ev = Events.from_columns([0, 0, 0, 1], [0, 0, 0, 0], [1, 2, 2, 5], [1, 1, 1, 0])
        >>> knots, change = next_knots(ev, torch.tensor([1, 1, 1, -1]), before=torch.tensor(4),
        ...                            keep=1, width=2)
        >>> knots.t.tolist(), knots.x.tolist(), change.tolist()
        ([2, 5], [0, 1], [3, -1])
    """
    t_dtype = window.t.dtype
    if window.num_events == 0:
        empty = Events.empty(t_dtype)
        return empty, empty.x.clone()
    if t_dtype not in TIME_DTYPES:
        raise TypeError(f"next_knots takes int64, float64 or float32 timestamps, got {t_dtype}")
    x, y, t, steps = columns_of(window.x, window.y, window.t, change)
    n = t.shape[0]
    work = tuple(scratch_column(f"next knots {i}", n, np.int64) for i in range(8))
    status, *out = _next_loop(x, y, t, steps, _scalar(before, t_dtype), keep, width, work,
                              scratch_column("next knots kept", n, np.bool_))
    if status < 0:
        raise ValueError("next_knots needs non-negative pixel ids y * width + x")
    knot_x, knot_y, knot_t, knot_p, knot_change = (torch.from_numpy(column) for column in out)
    return Events(knot_x, knot_y, knot_t, knot_p), knot_change
