"""Event funnelling kernel: downsample, then drop repeated events."""

from __future__ import annotations

import torch

from evdown_torch._tensors import changes, chunk_bounds, region_of, sort_by_time
from evdown_torch.events import Events

__all__ = ["event_funnelling"]


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
    # the first occurrence of each first.
    sorted_key, order = torch.sort(key, stable=True)
    first = changes(sorted_key)
    duplicates = order[~first]
    if duplicates.shape[0] == 0:
        return Events(x, y, events.t.clone(), events.p.clone())
    keep = torch.ones(n, dtype=torch.bool, device=events.device)
    keep[duplicates] = False
    index = keep.nonzero().squeeze(1)
    return Events(x[index], y[index], events.t[index], events.p[index])
