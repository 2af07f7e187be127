"""The held knots of a bounded delay, shared by the linear and cubic estimators.

With a bounded delay ``D`` (``max_delay``, docs/semantics.md "Bounded delay"), a knot
``(t_next - D, previous level)`` is inserted wherever two consecutive knots of a pixel (the
front knot included) are more than ``D`` apart (:func:`hold_knots`): the estimators see it as
an event that changes no level, so the knot and breakpoint machinery of :mod:`.knots` stays one.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from evdown_torch._regions import region_xy
from evdown_torch._tensors import (
    changes,
    searchsorted_ascending,
    stable_sort_small,
    take,
    time_order,
    where_true,
)
from evdown_torch.checks import MAX_EXACT_SPAN
from evdown_torch.events import Events, polarity_sign

__all__ = [
    "SMALL_WINDOW",
    "check_max_delay",
    "effective_delay",
    "held_knots",
    "hold_knots",
    "merge_by_time",
]


def check_max_delay(max_delay: float | None, t: Tensor) -> None:
    """Refuse a ``max_delay`` that is not a whole number for integer timestamps."""
    if max_delay is not None and not t.is_floating_point() and max_delay != math.floor(max_delay):
        raise ValueError(
            "max_delay must be a whole number for integer timestamps (held knots must fall "
            f"on ticks), got {max_delay!r}"
        )


def effective_delay(max_delay: float, t: Tensor) -> int | float:
    """``D`` as the kernels use it: a float for float ``t``, an int for integer ``t``.

    For integer ``t`` a delay of :data:`~evdown_torch.checks.MAX_EXACT_SPAN` or more is
    taken as exactly that: every gap between knots of a stream the estimators accept is
    shorter (:func:`check_span`), so such a delay holds no knot either way ("never hold"),
    and the int64 arithmetic on it (``t - D``, ``tau - lag * D``) cannot overflow. A float
    delay is used as it is (float arithmetic saturates to infinities instead of wrapping).

    Example:
        >>> effective_delay(1e300, torch.tensor([0])), effective_delay(7.0, torch.tensor([0]))
        (9007199254740992, 7)
    """
    check_max_delay(max_delay, t)
    if t.is_floating_point():
        return max_delay
    return MAX_EXACT_SPAN if max_delay >= MAX_EXACT_SPAN else int(max_delay)


def hold_knots(
    events: Events, *, max_delay: float, t_start: Tensor,
    upkeep: tuple[Callable[..., Events], Callable[..., tuple[Events, Tensor]]] | None = None,
) -> tuple[Events, Tensor]:
    """The stream with the held knots of a bounded delay added, and each event's level change.

    Wherever two consecutive knots of a pixel (its front knot ``(t_start, 0)`` included) are
    more than ``max_delay`` apart, a held knot at ``t_next - max_delay`` is added as an event
    with level change 0 (docs/semantics.md, "Bounded delay").

    Args:
        events: ``N`` events (put in stable time order here when they are not).
        max_delay: ``D`` > 0, in the stream's time unit (a whole number for int64 ``t``).
        t_start: ``()`` first timestamp of the whole stream, or ``(N,)`` for each event that
            of its own stream (a batch of recordings, see :func:`.driver.estimate`) or the
            time of its pixel's last knot before these events (a streaming session's next
            chunk).
        upkeep: the ``(held_knots, merge_by_time)`` to use (the compiled twins give the same
            tensors), or ``None`` for this module's.

    Returns:
        ``(events, change)``: ``N + M`` events in stable time order (a held knot before the
        real events of its timestamp) and their ``(N + M,)`` int8 level changes (+1, -1, 0).

    Example:
        >>> ev = Events.from_columns([0, 0, 1], [0, 0, 0], [0, 10, 4], [1, 1, 0])
        >>> held, change = hold_knots(ev, max_delay=3, t_start=ev.t[0])
        >>> held.t.tolist(), held.x.tolist(), change.tolist()
        ([0, 1, 4, 7, 10], [0, 1, 1, 0, 0], [1, 0, -1, 0, 1])
    """
    by_time = time_order(events.t)  # None when already in time order (the callers')
    if by_time is not None:
        events = events.select(by_time)
        t_start = t_start if t_start.ndim == 0 else take(t_start, by_time)
    change = polarity_sign(events.p)
    held_of, merge = upkeep if upkeep is not None else (held_knots, merge_by_time)
    held = held_of(events, max_delay=max_delay, t_start=t_start)
    m = held.num_events
    if m == 0:
        return events, change
    # Merged in time order, a held knot before the real events of its time.
    return merge([(held, torch.zeros(m, dtype=change.dtype, device=change.device)),
                  (events, change)])


def held_knots(events: Events, *, max_delay: float, t_start: Tensor) -> Events:
    """The held knots of a bounded delay alone (see :func:`hold_knots`), sorted by time.

    Args:
        events: ``N`` events in stable time order.
        max_delay: as for :func:`hold_knots`.
        t_start: as for :func:`hold_knots`.

    Returns:
        ``M`` held knots in stable time order (ties in pixel order), polarity ``False``.

    Example:
        >>> ev = Events.from_columns([0, 1, 0], [0, 0, 0], [0, 4, 10], [1, 0, 1])
        >>> held = held_knots(ev, max_delay=3, t_start=ev.t[0])
        >>> held.t.tolist(), held.x.tolist()
        ([1, 7], [1, 0])
    """
    delay = effective_delay(max_delay, events.t)
    n = events.num_events
    if n == 0:
        return events
    # Events in pixel order then time order: a knot is held where an event is more than D
    # after its pixel's previous event (the front knot's t_start before the first); events of
    # one knot time are 0 apart, so only the first event of each knot can be held.
    width = int(events.x.max()) + 1
    pixel = events.y * width + events.x
    pixel, order = stable_sort_small(pixel)
    t = take(events.t, order)
    new_pixel = changes(pixel)
    previous = torch.empty_like(t)
    previous[1:] = t[:-1]
    first_at = where_true(new_pixel)
    start = t_start if t_start.ndim == 0 else take(t_start, take(order, first_at))
    previous.index_put_((first_at,), start)  # a gap of 0 where the pixel starts at t_start
    held_at = where_true((t - previous) > delay)
    del previous
    held_pixel = take(pixel, held_at)
    held_t, held_order = torch.sort(take(t, held_at) - delay, stable=True)
    held_pixel = take(held_pixel, held_order)
    held_x, held_y = region_xy(held_pixel, width)
    return Events(held_x, held_y, held_t,
                  torch.zeros(held_t.shape[0], dtype=torch.bool, device=t.device))


#: Windows (knot events) below which a merge sorts them whole and a session's step trims them
#: whole: fewer operations than :func:`merge_by_time` and the session's ``_recent``, which
#: pay on larger ones.
SMALL_WINDOW = 1 << 12


def merge_by_time(parts: list[tuple[Events, Tensor]]) -> tuple[Events, Tensor]:
    """Time-sorted knot events and their level changes, merged as a stable time sort of them.

    A tie keeps the parts' order, as a stable sort of their concatenation would. Each element
    moves up by the elements of the other parts that come before it: a binary search of its
    time in each smaller part; the largest part is searched in instead, and its elements
    counted up by a cumulative sum.
    """
    sizes = [events.num_events for events, _ in parts]
    if sum(sizes) < SMALL_WINDOW:  # fewer operations; the same order
        events = Events.cat([part for part, _ in parts])
        order = torch.sort(events.t, stable=True).indices
        return events.select(order), take(torch.cat([change for _, change in parts]), order)
    big = max(range(len(parts)), key=sizes.__getitem__)
    big_t = parts[big][0].t
    device = big_t.device
    position = [torch.arange(size, device=device) for size in sizes]
    before_big = torch.zeros(sizes[big] + 1, dtype=torch.int64, device=device)
    for i, (events, _) in enumerate(parts):
        if i == big:
            continue
        for j, (other, _) in enumerate(parts):
            if j not in (i, big):
                position[i] += _count_before(other.t, events.t, right=j < i)
        after = _count_before(big_t, events.t, right=big < i)  # big's elements before
        position[i] += after
        if isinstance(after, int):
            before_big[after] += sizes[i]
        else:
            before_big += torch.bincount(after, minlength=sizes[big] + 1)
    position[big] += torch.cumsum(before_big, 0)[:-1]
    total = sum(sizes)

    def column(values: list[Tensor]) -> Tensor:  # each part's values put at their positions
        out = torch.empty(total, dtype=values[0].dtype, device=device)
        for at, part in zip(position, values, strict=True):
            out.index_copy_(0, at, part)
        return out

    change = column([change for _, change in parts])
    # The polarity is not read where level changes are given; it says which raise the level.
    x, y, t = (column([events[c] for events, _ in parts]) for c in range(3))
    return Events(x, y, t, change > 0), change


def _count_before(ordered: Tensor, t: Tensor, *, right: bool) -> Tensor | int:
    """``searchsorted(ordered, t, right=right)`` for sorted ``t``, or the count all share.

    When the two ranges of times do not overlap (a session's earlier knots all come before
    its chunk's events), every ``t`` has the same count, returned as an int.
    """
    n = ordered.shape[0]
    if n == 0 or t.shape[0] == 0:
        return 0
    if t[-1] < ordered[0] or (not right and t[-1] == ordered[0]):
        return 0
    if t[0] > ordered[-1] or (right and t[0] == ordered[-1]):
        return n
    return searchsorted_ascending(ordered, t, right=right)
