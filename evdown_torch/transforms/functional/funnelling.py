"""Event funnelling kernel: downsample, then drop repeated events."""

from __future__ import annotations

import torch

from evdown_torch._tensors import (
    changes,
    chunk_bounds,
    region_of,
    sort_by_time,
    stable_sort_small,
)
from evdown_torch.events import Events

__all__ = ["drop_repeats", "event_funnelling"]


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
    bounds = chunk_bounds(events.t, split_ties=False)
    pieces = [
        _funnel_sorted(Events(*(column[start:stop] for column in events)), factor)
        for start, stop in zip(bounds[:-1], bounds[1:])
    ]
    if len(pieces) == 1:
        return pieces[0]
    return Events(*(torch.cat(columns) for columns in zip(*pieces)))


def drop_repeats(events: Events, *, seen: Events | None = None) -> Events:
    """Drop every event equal in ``(x, y, t, p)`` to an earlier one or to one of ``seen``.

    The step both funnelling methods stream with: ``seen`` holds the distinct events kept at
    the previous chunk's last timestamp (the only ones a later chunk can repeat).

    Args:
        events: ``N`` time-sorted events.
        seen: distinct events kept earlier, all at a timestamp ``<=`` the first of ``events``
            (``None``: none).

    Returns:
        The events of ``events`` that repeat nothing, in their order.

    Example:
        >>> seen = Events.from_columns([1], [0], [5], [1])
        >>> ev = Events.from_columns([1, 1, 0, 1], [0, 0, 0, 0], [5, 5, 5, 6], [1, 0, 1, 1])
        >>> drop_repeats(ev, seen=seen).x.tolist()
        [1, 0, 1]
    """
    skip = 0 if seen is None else seen.num_events
    if skip:
        events = Events(*(torch.cat(pair) for pair in zip(seen, events)))
    bounds = chunk_bounds(events.t, split_ties=False)
    pieces = [
        _funnel_sorted(Events(*(column[start:stop] for column in events)), (1, 1))
        for start, stop in zip(bounds[:-1], bounds[1:])
    ]
    out = pieces[0] if len(pieces) == 1 else Events(*(torch.cat(c) for c in zip(*pieces)))
    # The distinct ``seen`` events come first and are all kept: drop them again.
    return Events(*(column[skip:] for column in out)) if skip else out


def last_instant(events: Events, previous: Events | None) -> Events | None:
    """The events at the latest timestamp of ``previous`` followed by ``events`` (time-sorted).

    What a funnelling session keeps for the next chunk; ``previous`` when ``events`` is empty.
    """
    if events.num_events == 0:
        return previous
    last = events.t[-1]
    start = int(torch.searchsorted(events.t, last.reshape(1), side="left"))
    tail = Events(*(column[start:] for column in events))
    if start == 0 and previous is not None and bool(previous.t[-1] == last):
        tail = Events(*(torch.cat(pair) for pair in zip(previous, tail)))
    return tail


def _funnel_sorted(events: Events, factor: tuple[int, int]) -> Events:
    """:func:`event_funnelling` on time-sorted events (duplicates share ``t``, so chunks that
    never split a run of equal timestamps can be funnelled one by one)."""
    n = events.num_events
    x, y = region_of(events, factor)
    if n < 2:
        return Events(x, y, events.t.clone(), events.p.clone())
    # Dense rank of t (t is sorted), then one int64 key per (t, x', y', p), built in place.
    key = torch.cumsum(changes(events.t), 0)
    width = int(x.max()) + 1
    height = int(y.max()) + 1
    key.mul_(height).add_(y).mul_(width).add_(x).mul_(2).add_(events.p)
    # Equal keys share t, so they lie in one run of equal t; a stable sort of the keys puts
    # the first occurrence of each first (as int32 when the keys fit: several times faster).
    bound = (int(key[-1]) + 1) * height * width * 2
    sorted_key, order = stable_sort_small(key, bound)
    first = changes(sorted_key)
    duplicates = order[~first]
    if duplicates.shape[0] == 0:
        return Events(x, y, events.t.clone(), events.p.clone())
    keep = torch.ones(n, dtype=torch.bool, device=events.device)
    keep[duplicates] = False
    index = keep.nonzero().squeeze(1)
    return Events(x[index], y[index], events.t[index], events.p[index])
