"""Log-luminance event count kernel, integer-exact and causal, with streaming state."""

from __future__ import annotations

import functools
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._regions import region_pixel_count, region_xy
from evdown_torch._tensors import (
    changes,
    chunk_bounds,
    continued_cumsum,
    divide,
    ends,
    floor_divide_exact,
    stable_sort_small,
    take,
)
from evdown_torch.checks import check_state_memory, output_size
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events, polarity_sign, sort_by_time
from evdown_torch.transforms.functional.batch import Stacked, run_stacked, sorted_within
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.protocol import Method
from evdown_torch.transforms.functional.reference import (
    capped_threshold,
    move_crossings,
    region_dtype,
    region_runs,
    threshold_fraction,
)
from evdown_torch.transforms.functional.settings import RegionSettings, ThresholdSettings

__all__ = [
    "EVENT_COUNT",
    "EventCountState",
    "event_count",
    "event_count_batch",
    "event_count_init",
    "event_count_stacked",
    "event_count_step",
    "event_count_whole",
]


class EventCountState(NamedTuple):
    """State of every output region between chunks of a stream.

    Attributes:
        level_sum: ``(Ho * Wo,)`` int64 sum of the region's pixel levels (ON +1, OFF -1).
        reference: ``(Ho * Wo,)`` int64 reference index ``q`` of each region.
    """

    level_sum: Tensor
    reference: Tensor


def initial_state(
    settings: RegionSettings, device: torch.device | str | None = None, recordings: int = 1
) -> EventCountState:
    """A fresh state: every region at level 0 with reference index 0.

    The regions are those of each of ``recordings`` stacked recordings.
    """
    out_w, out_h, _ = settings.output_sensor_size
    check_state_memory("EventCount", settings.sensor_size, settings.factor, region_bytes=16,
                       recordings=recordings, device=device)  # two int64 per region
    zeros = torch.zeros(out_w * out_h * recordings, dtype=torch.int64, device=device)
    return EventCountState(zeros, zeros.clone())


def event_count(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    threshold: float,
) -> Events:
    """Downscale by the log-luminance event count (docs/semantics.md, method 3).

    Each pixel keeps an integer level (ON adds 1, OFF subtracts 1). After each input event, in
    stable time order, its region's mean level ``M_r = sum(L_p) / n_r`` is tested with the
    DVS reference rule against ``threshold``; emitted events take the triggering event's
    ``t``. Levels are compared in exact integer arithmetic: ``threshold`` is taken as the
    rational ``a / b`` of ``threshold_fraction``, and ``b * sum(L_p)`` is compared with
    ``a * n_r * k``.

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        threshold: contrast threshold ``theta`` on the region's mean level, > 0.

    Returns:
        Output events sorted by ``t``. A stream in chunks goes through
        :data:`EVENT_COUNT`'s ``init_state`` and ``step`` (a transform's session).

    Example:
        >>> ev = Events.from_columns([0, 1, 0, 1], [0, 0, 0, 1], [1, 2, 3, 4], [1, 1, 0, 0])
        >>> out = event_count(ev, sensor_size=(2, 2, 2), factor=(2, 2), threshold=0.5)
        >>> out.t.tolist(), out.p.tolist()
        ([2, 4], [True, False])
    """
    return event_count_whole(events, ThresholdSettings(sensor_size, factor, threshold))


def event_count_init(settings: ThresholdSettings, events: Events) -> EventCountState:
    """EventCount's ``init_state``: every region at level 0, reference index 0."""
    return initial_state(settings, events.device)


def event_count_step(
    events: Events, state: EventCountState, settings: ThresholdSettings
) -> tuple[Events, EventCountState]:
    """EventCount's ``step``: causal, so every output is decided by its (time-sorted) chunk.

    On the CPU, the compiled loop of :mod:`.compiled.event_count` (the same events and state)
    runs unless the eager kernels are forced (:func:`.compiled.use_compiled`).

    Returns:
        ``(output events sorted by t, state after the chunk's last event)``.
    """
    if use_compiled(events.t):
        from evdown_torch.transforms.functional.compiled import event_count as compiled

        out, (level_sum, reference) = compiled.event_count_step(events, state, settings)
        return out, EventCountState(level_sum, reference)
    bounds = chunk_bounds(events.t)
    if len(bounds) == 2:
        return _event_count_sorted(events, settings, state)
    # A long stream goes through in chunks, exactly as a streaming session would.
    outputs = []
    emitted = 0
    for start, stop in zip(bounds[:-1], bounds[1:]):
        piece = events.part(start, stop)
        out, state = _event_count_sorted(piece, settings, state, emitted)
        outputs.append(out)
        emitted += out.num_events
    return Events.cat(outputs), state


def event_count_whole(events: Events, settings: ThresholdSettings) -> Events:
    """The whole stream (any order)."""
    state = initial_state(settings, events.device)
    out, _ = event_count_step(sort_by_time(events), state, settings)
    return out


def event_count_batch(
    events: Events, lengths: tuple[int, ...], settings: ThresholdSettings
) -> tuple[Events, tuple[int, ...]]:
    """:func:`event_count` of each of a batch of recordings, each in time order, in one pass.

    The recordings are not moved onto a virtual sensor or clock: recording ``b``'s regions
    are the block ``[b * Ho * Wo, (b + 1) * Ho * Wo)`` of region ids (as in
    ``transforms.functional.batch``'s stacking), its events are taken in the batch's
    order (recording after recording), and its output comes back in its own coordinates.

    Args:
        events: the recordings' events concatenated, recording 0 first, each recording sorted
            by ``t`` (:func:`~evdown_torch.transforms.functional.batch.sorted_within`).
        lengths: number of events of each recording.
        settings: the method's settings.

    Returns:
        ``(outputs, output count of each recording)``: each recording's :func:`event_count`
        output, concatenated.

    Example:
        >>> ev = Events.from_columns([0, 1, 0, 1], [0, 0, 0, 1], [1, 2, 1, 2], [1, 1, 1, 1])
        >>> out, counts = event_count_batch(ev, (2, 2), ThresholdSettings((2, 2, 2), 2, 0.5))
        >>> out.t.tolist(), counts
        ([2, 2], (1, 1))
    """
    if use_compiled(events.t):
        from evdown_torch.transforms.functional.compiled import event_count as compiled

        fresh = initial_state(settings, events.device, len(lengths))
        return compiled.event_count_batch(events, lengths, settings, fresh)
    device = events.device
    sensor_size, factor = settings.sensor_size, settings.factor
    recordings = len(lengths)
    state = initial_state(settings, device, recordings)
    out_w, out_h, _ = output_size(sensor_size, factor)
    block_size = out_w * out_h
    narrow = region_dtype(sensor_size, factor, block_size * recordings)
    counts = torch.tensor(lengths, dtype=torch.int64, device=device)
    recording_offset = torch.repeat_interleave(
        torch.arange(0, block_size * recordings, block_size, dtype=narrow, device=device),
        counts, output_size=events.num_events)
    bounds = chunk_bounds(events.t)
    outputs = []
    emitted = 0
    for start, stop in zip(bounds[:-1], bounds[1:]):
        piece = events.part(start, stop)
        out, state = _event_count_sorted(piece, settings, state, emitted,
                                         recording_offset=recording_offset[start:stop])
        outputs.append(out)
        emitted += out.num_events
    out = outputs[0] if len(outputs) == 1 else Events.cat(outputs)
    # The output is in the batch's order: recording after recording, each on its block's rows.
    recording = divide(out.y, out_h)
    out_counts = tuple(torch.bincount(recording, minlength=recordings).tolist())
    return Events(out.x, out.y.sub_(recording, alpha=out_h), out.t, out.p), out_counts


def event_count_stacked(batch: EventBatch, settings: ThresholdSettings) -> EventBatch:
    """The kernel once on the batch, with one block of regions per recording.

    Recordings in time order need no stacking (:func:`event_count_batch`).
    """
    if sorted_within(batch.events.t, batch.lengths):
        return EventBatch(*event_count_batch(batch.events, batch.lengths, settings))

    def kernel(stacked: Stacked) -> Events:
        state = initial_state(settings, stacked.events.device, stacked.recordings)
        out, _ = event_count_step(sort_by_time(stacked.events), state, settings)
        return out

    return run_stacked(batch, kernel, sensor_size=settings.sensor_size, factor=settings.factor)


#: EventCount's kernels (:class:`~evdown_torch.EventCount`).
EVENT_COUNT: Method[ThresholdSettings, EventCountState] = Method(
    event_count_init, event_count_step, whole=event_count_whole, stacked=event_count_stacked
)


@functools.lru_cache(maxsize=32)
def _region_sizes(sensor_size: tuple[int, int, int], factor: tuple[int, int], regions: int,
                  device: torch.device) -> tuple[Tensor, int, bool]:
    """``n_r`` of every region (never written to), the largest, and whether all are equal.

    The same for every chunk of a stream: computed once, not per call (a live stream's small
    chunks would pay it each time).
    """
    pixels = region_pixel_count(torch.arange(regions, device=device), sensor_size, factor)
    most = int(pixels.max())
    return pixels, most, most == int(pixels.min())


def _event_count_sorted(
    events: Events,
    settings: ThresholdSettings,
    state: EventCountState,
    emitted: int = 0,
    recording_offset: Tensor | None = None,
) -> tuple[Events, EventCountState]:
    """:func:`event_count` on time-sorted events.

    ``emitted``: events of earlier chunks; ``recording_offset``: each event's first region id, in
    :func:`.reference.region_dtype`, for a batch's events in their own coordinates.

    Few passes over the events, on narrow dtypes (the cost of a live chunk is its memory
    traffic): the events are grouped by region with a small-key sort, each region's level sum
    is one running sum (its start corrected once per region), and the reference rule runs on
    the moves that can change ``q`` only (:func:`move_crossings`).
    """
    device = events.device
    n = events.num_events
    if n == 0:
        return Events.empty(events.t.dtype, device), state
    # No |M_r| can exceed the level sums it starts from plus one per event.
    bound = int(state.level_sum.abs().max()) + n if state.level_sum.numel() else n
    fraction = capped_threshold(threshold_fraction(settings.threshold), bound)
    a, b = fraction.numerator, fraction.denominator
    sensor_size, factor = settings.sensor_size, settings.factor
    out_w, _, _ = settings.output_sensor_size
    regions = state.level_sum.shape[0]  # Ho * Wo per stacked recording
    pixels, most, uniform = _region_sizes(sensor_size, factor, regions, device)
    # int32 arithmetic is exact when every b * S and a * n_r fits (the usual case).
    dtype = torch.int32 if 4 * bound * b < 2**31 and most * a < 2**31 else torch.int64

    # Group by region, time order kept inside each group: region ids computed in the narrowest
    # integer type that holds the coordinates and the ids (int16 for sensors up to 32,768).
    narrow = region_dtype(sensor_size, factor, regions)
    region_id = events.y.to(narrow, copy=True)
    divide(region_id, factor[1], out=region_id).mul_(out_w)
    column = events.x.to(narrow, copy=True)
    region_id += divide(column, factor[0], out=column)
    del column
    if recording_offset is not None:
        region_id += recording_offset
    region, order = stable_sort_small(region_id, regions, narrow=True)
    del region_id
    touched, firsts, lasts, first = region_runs(region, regions)  # regions with events

    # Level sum S of each region after each of its events: one running sum over the grouped
    # level changes (ON +1, OFF -1), each region's continued from its state.
    level_sum, final = continued_cumsum(polarity_sign(take(events.p, order), dtype), firsts,
                                        lasts, take(state.level_sum, touched).to(dtype))

    # u = M / theta = b * S / (a * n_r), compared in integers.
    new_sum = state.level_sum.clone()
    new_sum[touched] = final.to(torch.int64)
    numerator = level_sum.mul_(b) if b != 1 else level_sum
    if uniform:
        denominator: int | Tensor = most * a
    else:
        denominator = take((pixels * a).to(dtype), region.to(torch.int32))
    floor_u, on_level = floor_divide_exact(numerator, denominator)
    del numerator, level_sum
    q_first = None if not bool(state.reference.any()) else take(state.reference, touched)
    # With an integer threshold (b == 1) a move changes b * S by one: it lands on every level.
    cross = move_crossings(floor_u, on_level, first, emitted=emitted, q_first=q_first,
                           lands_on_levels=b == 1)

    # Back to time order: crossings of one move keep their level order.
    move_at = cross.move
    source, by_time = stable_sort_small(take(order, move_at), n)
    move_at = take(move_at, by_time)
    out_x, out_y = region_xy(take(region, move_at).to(torch.int64), out_w)
    out = Events(out_x, out_y, take(events.t, source), take(cross.on, by_time))

    # New state: each touched region's last sum, and the level of its last crossing.
    new_reference = state.reference.clone()
    if cross.move.shape[0]:
        crossed = take(region, cross.move).to(torch.int64)
        last = ends(changes(crossed))
        new_reference[crossed[last]] = cross.level[last].to(torch.int64)
    return out, EventCountState(new_sum, new_reference)
