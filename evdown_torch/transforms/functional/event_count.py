"""Log-luminance event count kernel, integer-exact and causal, with streaming state."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import (
    chunk_bounds,
    floor_divide_exact,
    region_of,
    region_pixel_count,
    region_xy,
    sort_by_time,
)
from evdown_torch.checks import output_size
from evdown_torch.events import Events
from evdown_torch.transforms.functional._reference import (
    capped_threshold,
    crossings,
    group_by_region,
    reference_index,
    threshold_fraction,
)

__all__ = ["EventCountState", "event_count", "initial_state"]


class EventCountState(NamedTuple):
    """State of every output region between chunks of a stream.

    Attributes:
        level_sum: ``(Ho * Wo,)`` int64 sum of the region's pixel levels (ON +1, OFF -1).
        index: ``(Ho * Wo,)`` int64 reference index ``q`` of each region.
        last_t: ``()`` tensor, the latest timestamp seen (``None`` before any event).
    """

    level_sum: Tensor
    index: Tensor
    last_t: Tensor | None


def initial_state(
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    device: torch.device | str | None = None,
    recordings: int = 1,
) -> EventCountState:
    """A fresh state: every region (of each of ``recordings`` stacked recordings) at level 0
    with reference index 0."""
    out_w, out_h, _ = output_size(sensor_size, factor)
    zeros = torch.zeros(out_w * out_h * recordings, dtype=torch.int64, device=device)
    return EventCountState(zeros, zeros.clone(), None)


def event_count(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    threshold: float,
    state: EventCountState | None = None,
    recordings: int = 1,
) -> tuple[Events, EventCountState]:
    """Downscale by the log-luminance event count (docs/semantics.md, method 3).

    Each pixel keeps an integer level (ON adds 1, OFF subtracts 1). After each input event, in
    stable time order, its region's mean level ``M_r = sum(L_p) / n_r`` is tested with the
    DVS reference rule against ``threshold``; emitted events take the triggering event's
    ``t``. Levels are compared in exact integer arithmetic: ``threshold`` is taken as the
    rational ``a / b`` of :func:`threshold_fraction`, and ``b * sum(L_p)`` is compared with
    ``a * n_r * k``.

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        threshold: contrast threshold ``theta`` on the region's mean level, > 0.
        state: the state returned for the previous chunk of the same stream, or ``None``
            for a fresh stream.
        recordings: ``B``, for a batch of recordings stacked vertically: recording ``b``'s
            pixel ``(x, y)`` given as ``(x, y + b * Ho * fy)`` (regions never mix recordings;
            see :mod:`evdown_torch.transforms._batch`). 1 for one stream.

    Returns:
        ``(output events sorted by t, state after the last event)``.

    Example:
        >>> ev = Events.from_columns([0, 1, 0, 1], [0, 0, 0, 1], [1, 2, 3, 4], [1, 1, 0, 0])
        >>> out, _ = event_count(ev, sensor_size=(2, 2, 2), factor=(2, 2), threshold=0.5)
        >>> out.t.tolist(), out.p.tolist()
        ([2, 4], [True, False])
    """
    events = sort_by_time(events)
    if state is None:
        state = initial_state(sensor_size, factor, events.device, recordings)
    bounds = chunk_bounds(events.t)
    if len(bounds) == 2:
        return _event_count_sorted(events, sensor_size, factor, threshold, state)
    # A long stream goes through in chunks, exactly as a streaming session would.
    outputs = []
    emitted = 0
    for start, stop in zip(bounds[:-1], bounds[1:]):
        piece = Events(*(column[start:stop] for column in events))
        out, state = _event_count_sorted(piece, sensor_size, factor, threshold, state, emitted)
        outputs.append(out)
        emitted += out.num_events
    return Events(*(torch.cat(columns) for columns in zip(*outputs))), state


def _event_count_sorted(
    events: Events,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    threshold: float,
    state: EventCountState,
    emitted: int = 0,
) -> tuple[Events, EventCountState]:
    """:func:`event_count` on time-sorted events (``emitted``: events of earlier chunks)."""
    device = events.device
    n = events.num_events
    if n == 0:
        return Events.empty(events.t.dtype, device), state
    # No |M_r| can exceed the level sums it starts from plus one per event.
    bound = int(state.level_sum.abs().max()) + n if state.level_sum.numel() else n
    fraction = capped_threshold(threshold_fraction(threshold), bound)
    a, b = fraction.numerator, fraction.denominator
    out_w, out_h, _ = output_size(sensor_size, factor)
    rx, ry = region_of(events, factor)
    groups = group_by_region(rx, ry, out_w)
    region = groups.region
    del rx, ry

    # Level sum S of each region after each of its events (exact int64): a running sum over
    # the grouped events, minus its value before the region's first event, plus the state.
    step = events.p[groups.order].to(torch.int64)
    step.mul_(2).sub_(1)
    level_sum = torch.cumsum(step, 0)
    firsts = groups.first.nonzero().squeeze(1)
    offset = state.level_sum.clone()
    offset[region[firsts]] -= level_sum[firsts] - step[firsts]
    level_sum += offset[region]

    # u = M / theta = b * S / (a * n_r), compared in integers.
    regions = state.level_sum.shape[0]  # Ho * Wo per stacked recording
    pixels = region_pixel_count(torch.arange(regions, device=device), sensor_size, factor)
    uniform = bool((pixels == pixels[0]).all())
    denominator = int(pixels[0]) * a if uniform else (pixels * a)[region]
    numerator = level_sum * b if b != 1 else level_sum
    floor_u, on_level = floor_divide_exact(numerator, denominator)
    fresh = not bool(state.index.any())
    q_start = torch.zeros((), dtype=torch.int64, device=device) if fresh else state.index[region]
    q = reference_index(floor_u, on_level, groups.first, q_start)

    q_before = q.roll(1)
    q_before[firsts] = state.index[region[firsts]]
    cross = crossings(q_before, q, emitted=emitted)

    # Back to time order: crossings of one step keep their level order.
    source, by_time = torch.sort(groups.order[cross.step], stable=True)
    out_x, out_y = region_xy(region[cross.step[by_time]], out_w)
    out = Events(out_x, out_y, events.t[source], cross.on[by_time])

    # New state: each touched region's last sum and index.
    lasts = torch.cat([firsts[1:] - 1, firsts.new_tensor([n - 1])])
    new_sum = state.level_sum.clone()
    new_index = state.index.clone()
    new_sum[region[lasts]] = level_sum[lasts]
    new_index[region[lasts]] = q[lasts]
    return out, EventCountState(new_sum, new_index, events.t[-1].clone())
