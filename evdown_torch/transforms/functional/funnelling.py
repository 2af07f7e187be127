"""Event funnelling kernel: downsample, then drop repeated events."""

from __future__ import annotations

import torch
from torch import Tensor

from evdown_torch._tensors import (
    changes,
    chunk_bounds,
    divide,
    narrow_dtype,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.checks import check_output_count
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events, sort_by_time
from evdown_torch.transforms.functional.batch import Stacked, run_stacked, sorted_within
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.downsample import to_regions
from evdown_torch.transforms.functional.protocol import Method
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = [
    "FUNNELLING",
    "drop_repeats",
    "event_funnelling",
    "funnelling_batch",
    "funnelling_init",
    "funnelling_sorted",
    "funnelling_stacked",
    "funnelling_step",
    "funnelling_whole",
    "key_grid",
    "last_instant",
]


#: How EventFunnelling's output gets under the output limit (a repeat shares its region).
FUNNEL_FEWER = "a larger factor gives fewer events"


def event_funnelling(events: Events, *, factor: tuple[int, int]) -> Events:
    """Downsample, then drop every event equal in ``(x', y', t, p)`` to an earlier one.

    Args:
        events: ``N`` events (any order).
        factor: ``(fx, fy)``, positive integers.

    Returns:
        The first event of each distinct ``(x', y', t, p)``, in stable time order.

    Example:
        >>> ev = Events.from_columns([0, 1, 2, 0], [0, 1, 0, 0], [5, 5, 5, 6], [1, 1, 1, 1])
        >>> out = event_funnelling(ev, factor=(2, 2))
        >>> out.x.tolist(), out.t.tolist()
        ([0, 1, 0], [5, 5, 6])
    """
    events = sort_by_time(events)
    # Repeats share t: pieces that never split a run of equal timestamps are independent.
    bounds = chunk_bounds(events.t, split_ties=False)
    pieces = [
        funnelling_sorted(events.part(start, stop), factor)
        for start, stop in zip(bounds[:-1], bounds[1:])
    ]
    if len(pieces) == 1:
        return pieces[0]
    return Events.cat(pieces)


def drop_repeats(
    events: Events, *, seen: Events | None = None, size: tuple[int, int] | None = None
) -> Events:
    """Drop every event equal in ``(x, y, t, p)`` to an earlier one or to one of ``seen``.

    The step both funnelling methods stream with: ``seen`` holds the distinct events kept at
    the previous chunk's last timestamp (the only ones a later chunk can repeat).

    Args:
        events: ``N`` time-sorted events.
        seen: distinct events kept earlier, all at a timestamp ``<=`` the first of ``events``
            (``None``: none).
        size: the sensor's ``(width, height)`` when known (every coordinate, ``seen``'s
            included, lies inside it); by default the largest coordinates + 1.

    Returns:
        The events of ``events`` that repeat nothing, in their order.

    Example:
        >>> seen = Events.from_columns([1], [0], [5], [1])
        >>> ev = Events.from_columns([1, 1, 0, 1], [0, 0, 0, 0], [5, 5, 5, 6], [1, 0, 1, 1])
        >>> drop_repeats(ev, seen=seen).x.tolist()
        [1, 0, 1]
    """
    bounds = chunk_bounds(events.t, split_ties=False)
    pieces = [
        funnelling_sorted(events.part(start, stop), (1, 1),
                          seen=seen if start == 0 else None, size=size)
        for start, stop in zip(bounds[:-1], bounds[1:])
    ]
    return pieces[0] if len(pieces) == 1 else Events.cat(pieces)


def funnelling_init(settings: RegionSettings, events: Events) -> Events | None:
    """EventFunnelling's ``init_state``: no output yet (``None``)."""
    return None


def funnelling_step(
    events: Events, state: Events | None, settings: RegionSettings
) -> tuple[Events, Events | None]:
    """EventFunnelling's ``step``: one time-sorted chunk.

    The state is the distinct output events at the latest timestamp so far: the only ones a
    later chunk can repeat (a repeat shares ``t``), so repeats that straddle a chunk boundary
    are still dropped.
    """
    width, height, _ = settings.output_sensor_size
    out = funnelling_sorted(events, settings.factor, seen=state, size=(width, height))
    check_output_count(out.num_events, fewer=FUNNEL_FEWER)  # at most the input: built already
    return out, last_instant(out, state)


def funnelling_whole(events: Events, settings: RegionSettings) -> Events:
    """EventFunnelling's whole-stream kernel (events in any order): :func:`event_funnelling`."""
    out = event_funnelling(events, factor=settings.factor)
    check_output_count(out.num_events, fewer=FUNNEL_FEWER)  # at most the input: built already
    return out


def last_instant(events: Events, previous: Events | None) -> Events | None:
    """The events at the latest timestamp of ``previous`` followed by ``events`` (time-sorted).

    What a funnelling session keeps for the next chunk; ``previous`` when ``events`` is empty.
    """
    if events.num_events == 0:
        return previous
    last = events.t[-1]
    start = int(torch.searchsorted(events.t, last.reshape(1), side="left"))
    tail = events.part(start)
    if start == 0 and previous is not None and bool(previous.t[-1] == last):
        tail = Events.cat([previous, tail])
    return tail


def funnelling_batch(
    events: Events, lengths: tuple[int, ...], factor: tuple[int, int], size: tuple[int, int]
) -> tuple[Events, tuple[int, ...]]:
    """:func:`event_funnelling` of each of a batch of recordings, each in time order.

    No recording index enters the key: the key stays that of one recording (a one-byte
    sort for sensors of up to 128 output pixels), and an event repeats its predecessor in key
    order when both lie in one run of equal ``(recording, t)`` (the runs are numbered in the
    batch's order: recording after recording, each in time order).

    Args:
        events: the recordings' events concatenated, recording 0 first, each recording sorted
            by ``t`` (:func:`~evdown_torch.transforms.functional.batch.sorted_within`).
        lengths: number of events of each recording.
        factor: ``(fx, fy)``.
        size: one recording's output ``(width, height)``.

    Returns:
        ``(kept events in output coordinates, kept count of each recording)``: each
        recording's :func:`event_funnelling` output, concatenated.

    Example:
        >>> ev = Events.from_columns([0, 1, 0, 1], [0, 0, 0, 0], [5, 5, 5, 5], [1, 1, 1, 1])
        >>> out, counts = funnelling_batch(ev, (2, 2), (2, 2), (1, 1))
        >>> out.t.tolist(), counts
        ([5, 5], (1, 1))
    """
    n = events.num_events
    if n == 0:
        return funnelling_sorted(events, factor, size=size), lengths
    if use_compiled(events.t):
        from evdown_torch.transforms.functional.compiled import funnelling as compiled

        done = compiled.funnelling_batch(events, lengths, factor, size)
        if done is not None:
            return done
    runs = changes(events.t)
    ends = torch.tensor(lengths, dtype=torch.int64).cumsum(0)
    starts = ends[:-1][ends[:-1] < n].to(events.device)
    runs.index_fill_(0, starts, True)  # a recording starts a run of its own
    runs = torch.cumsum(runs, 0, dtype=torch.int32 if n < 1 << 31 else torch.int64)
    # Repeats share their run: pieces that never split a run are independent. Only their
    # repeat flags are kept; the output is built once (no concatenation of pieces).
    bounds = chunk_bounds(runs, split_ties=False)
    if len(bounds) == 2:
        x, y, repeat = _repeats(events, factor, size=size, runs=runs)
        kept = _kept(events, x, y, repeat)
    else:
        repeat = None
        for start, stop in zip(bounds[:-1], bounds[1:]):
            piece = events.part(start, stop)
            _, _, flags = _repeats(piece, factor, size=size, runs=runs[start:stop])
            if flags is not None:
                if repeat is None:
                    repeat = torch.zeros(n, dtype=torch.bool, device=events.device)
                repeat[start:stop] = flags
        kept = _kept(events, divide(events.x, factor[0]), divide(events.y, factor[1]), repeat)
    if repeat is None:
        return kept, lengths
    # Drops per recording, by the recording each dropped event's position falls in.
    where = torch.searchsorted(ends.to(events.device), where_true(repeat), right=True)
    lost = torch.bincount(where, minlength=len(lengths)).tolist()
    return kept, tuple(length - drop for length, drop in zip(lengths, lost))


def funnelling_sorted(
    events: Events,
    factor: tuple[int, int],
    *,
    seen: Events | None = None,
    size: tuple[int, int] | None = None,
) -> Events:
    """Downsample time-sorted events and drop repeats, of each other and of ``seen``.

    Repeats share ``t``, so a stable sort of the small key ``(x', y', p)`` alone lines them
    up: inside one key the events stay in time order, and an event repeats an earlier one
    exactly when its predecessor in that order has the same key and the same ``t``. The key
    sort is a radix sort of int16 (int32 for sensors of over 16,384 output pixels) keys.

    Args:
        events: ``N`` time-sorted events.
        factor: ``(fx, fy)``; ``(1, 1)`` for events already in output coordinates.
        seen: distinct events in output coordinates, all at a timestamp ``<=`` the first of
            ``events`` (the kept events of a stream's latest timestamp so far), or ``None``.
        size: the output sensor's ``(width, height)`` when known (every output coordinate,
            ``seen``'s included, lies inside it); by default the largest coordinates + 1.

    Returns:
        The kept events in output coordinates (new tensors), in their order. On the CPU, from
        the compiled loop of :mod:`.compiled.funnelling` (for output grids up to its
        ``DENSE_KEYS``) unless the eager kernels are forced (:func:`.compiled.use_compiled`).
    """
    if events.num_events and use_compiled(events.t):
        from evdown_torch.transforms.functional.compiled import funnelling as compiled

        size = key_grid(events, factor, seen, size)
        out = compiled.funnelling_sorted(events, factor, seen=seen, size=size)
        if out is not None:
            return out
    if events.num_events == 0:
        return to_regions(events, factor)
    x, y, repeat = _repeats(events, factor, seen=seen, size=size)
    return _kept(events, x, y, repeat)


def key_grid(
    events: Events, factor: tuple[int, int], seen: Events | None, size: tuple[int, int] | None
) -> tuple[int, int]:
    """The output grid ``(width, height)`` of the keys of :func:`funnelling_sorted`'s events.

    ``size`` when given, else the largest output coordinates of ``N >= 1`` ``events`` (and
    ``seen``'s columns) + 1.
    """
    if size is not None:
        return size
    fx, fy = factor
    width, height = int(events.x.max()) // fx + 1, int(events.y.max()) // fy + 1
    if seen is not None and seen.num_events:
        width = max(width, int(seen.x.max()) + 1)
    return width, height


def _repeats(
    events: Events,
    factor: tuple[int, int],
    *,
    seen: Events | None = None,
    size: tuple[int, int] | None = None,
    runs: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """:func:`funnelling_sorted`'s output coordinates and repeat flags of ``N >= 1`` events.

    The coordinates are of a narrow dtype, the flags ``None`` when nothing repeats. ``runs``,
    when given, replaces ``t`` as what repeats share (:func:`funnelling_batch`).
    """
    n = events.num_events
    fx, fy = factor
    width, height = key_grid(events, factor, seen, size)
    # Output coordinates and keys in the narrowest integer type that holds them (int16 for
    # sensors up to 128x128 output pixels): a quarter of the memory traffic of int64.
    narrow = narrow_dtype(max(2 * width * height, width * fx, height * fy))
    x = events.x.to(narrow, copy=True)
    y = events.y.to(narrow, copy=True)
    if fx != 1:
        divide(x, fx, out=x)
    if fy != 1:
        divide(y, fy, out=y)
    repeat = None
    if n > 1:
        key = y * (2 * width)
        key.add_(x, alpha=2).add_(events.p)
        sorted_key, order = stable_sort_small(key, 2 * width * height, narrow=True)
        del key
        sorted_t = take(events.t if runs is None else runs, order)
        same = torch.zeros(n, dtype=torch.bool, device=events.device)
        torch.eq(sorted_key[1:], sorted_key[:-1], out=same[1:])
        same[1:] &= sorted_t[1:] == sorted_t[:-1]
        del sorted_key, sorted_t
        repeat = torch.empty_like(same).scatter_(0, order, same)
        del same, order
    if seen is not None and seen.num_events:
        # Only the chunk's head, at the stream's latest timestamp so far, can repeat ``seen``.
        head = int(torch.searchsorted(events.t, seen.t[-1:], side="right"))
        if head:
            seen_key = seen.y * (2 * width) + seen.x * 2 + seen.p
            head_key = y[:head].to(torch.int64) * (2 * width) + x[:head] * 2 + events.p[:head]
            again = torch.isin(head_key, seen_key)
            if repeat is None:
                repeat = torch.zeros(n, dtype=torch.bool, device=events.device)
            repeat[:head] |= again
    if repeat is not None and not bool(repeat.any()):
        repeat = None
    return x, y, repeat


def _kept(events: Events, x: Tensor, y: Tensor, repeat: Tensor | None) -> Events:
    """The events not flagged ``repeat``, with output coordinates ``x``, ``y``.

    Every column is a new tensor; the coordinates are int64.
    """
    if repeat is None:
        kept = Events(x, y, events.t.clone(), events.p.clone())
    else:
        kept = _compact(Events(x, y, events.t, events.p), ~repeat)
    return Events(kept.x.to(torch.int64), kept.y.to(torch.int64), kept.t, kept.p)


def _compact(events: Events, keep: Tensor) -> Events:
    """The events where ``keep``, as new tensors, in their order.

    A running count gives each kept event its slot (1, 2, ...; dropped ones all go to slot
    0, which is discarded), and every column is scattered there in one pass: no branch per
    event (``nonzero`` and masked selection branch on every event, several times slower).
    """
    slot = torch.cumsum(keep, 0)
    kept = int(slot[-1])
    slot.mul_(keep)
    return Events(*(
        torch.empty(kept + 1, dtype=column.dtype, device=column.device)
        .scatter_(0, slot, column)[1:]
        for column in events
    ))


def funnelling_stacked(batch: EventBatch, settings: RegionSettings) -> EventBatch:
    """A batch in one call.

    Recordings each in time order go through :func:`funnelling_batch` (no stacking); others
    through :func:`funnelling_whole` once on the stacked batch.
    """
    if sorted_within(batch.events.t, batch.lengths):
        width, height, _ = settings.output_sensor_size
        out = EventBatch(*funnelling_batch(batch.events, batch.lengths, settings.factor,
                                           (width, height)))
        check_output_count(out.events.num_events, fewer=FUNNEL_FEWER)
        return out

    def kernel(stacked: Stacked) -> Events:
        return funnelling_whole(stacked.events, settings)

    return run_stacked(batch, kernel, sensor_size=settings.sensor_size, factor=settings.factor)


#: EventFunnelling's kernels (:class:`~evdown_torch.EventFunnelling`); the state is the output
#: at the latest timestamp so far.
FUNNELLING: Method[RegionSettings, Events | None] = Method(
    funnelling_init, funnelling_step, whole=funnelling_whole, stacked=funnelling_stacked
)
