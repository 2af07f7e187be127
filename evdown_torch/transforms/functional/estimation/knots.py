"""Knots of a pixel and region breakpoints, shared by the linear and cubic estimators.

``docs/semantics.md``, methods 4 and 5: each pixel's log-luminance is a curve through its
*knots*, one per distinct time at which the pixel has events, at the level after all its events
at that time (ON +1, OFF -1), plus a front knot ``(t_start, 0)`` when the pixel's first event is
later than ``t_start`` and a back knot ``(t_end, last level)`` when its last knot is earlier than
``t_end``. So every active pixel's curve spans exactly ``[t_start, t_end]``; a pixel without
events stays at level 0 and is not represented.

A region's mean curve ``M_r`` has its breakpoints at the union of its pixels' knot times.
Regions do not interact, so the estimators take them in chunks of whole regions
(:func:`region_chunks`); for each chunk this module builds, without a Python loop over events,
pixels or regions (:func:`pixel_knots`):

* the knots of every active pixel in *pixel order* (grouped by region, then by pixel, then in
  time order), and
* the breakpoints of every active region (grouped by region, in time order; the first is at
  ``t_start``, the last at ``t_end``), with the breakpoint index of every knot.

With a bounded delay ``D`` the held knots are added before this module sees the stream
(:mod:`.delay`), as events that change no level, so the knot and breakpoint machinery stays one.

It also holds the output assembly both estimators share (:func:`emit`); the level test and
the reference rule they apply live in :mod:`~evdown_torch.transforms.functional.reference`.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._regions import pixel_columns, region_of, region_pixel_count, region_xy
from evdown_torch._tensors import (
    CHUNK_EVENTS,
    changes,
    differences,
    ends,
    last_of_runs,
    run_index,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.checks import check_time_span
from evdown_torch.events import Events, polarity_sign

__all__ = [
    "HALF_TOLERANCE",
    "RELATIVE_ERROR",
    "Knots",
    "RegionChunk",
    "check_span",
    "emit",
    "level_changes",
    "piece_time",
    "pixel_knots",
    "region_chunks",
    "region_pixels",
]

#: Integer crossing times: an offset this close below a half tick rounds up (see piece_time).
HALF_TOLERANCE = 1e-9

#: Integer crossing times: the float error of a crossing's offset in its piece, as a fraction
#: of the piece's length, that still rounds a tie up (derived in piece_time).
RELATIVE_ERROR = 32 * 2.0**-53


class Knots(NamedTuple):
    """Knots of every active pixel and breakpoints of every active region.

    ``K`` knots in pixel order (regions ascending, pixels ascending inside a region, time
    ascending inside a pixel); ``B`` breakpoints in region order, time ascending inside a
    region.

    Attributes:
        t: ``(K,)`` knot times, the dtype of the events' ``t``.
        level: ``(K,)`` int64 pixel level at the knot (events counted ON +1, OFF -1).
        first: ``(K,)`` bool, the knot is its pixel's first (always at ``t_start``).
        last: ``(K,)`` bool, the knot is its pixel's last (always at ``t_end``).
        breakpoint: ``(K,)`` int64 index of the region breakpoint at the knot's time.
        bp_t: ``(B,)`` breakpoint times, the dtype of the events' ``t``.
        bp_first: ``(B,)`` bool, the region's first breakpoint (at ``t_start``).
        bp_last: ``(B,)`` bool, the region's last breakpoint (at ``t_end``).
        regions: ``(R,)`` int64 ids ``ry * Wo + rx`` of the active regions, ascending.
        region_first_bp: ``(R,)`` int64 index of each active region's first breakpoint.
    """

    t: Tensor
    level: Tensor
    first: Tensor
    last: Tensor
    breakpoint: Tensor
    bp_t: Tensor
    bp_first: Tensor
    bp_last: Tensor
    regions: Tensor
    region_first_bp: Tensor

    def bp_region(self, bp: Tensor) -> Tensor:
        """Region id of the breakpoints ``bp`` (int64)."""
        rank = torch.searchsorted(self.region_first_bp, bp, right=True) - 1
        return take(self.regions, rank)


class RegionChunk(NamedTuple):
    """The events of consecutive output regions, in region-time order.

    Attributes:
        region: ``(n,)`` int64 region id ``ry * Wo + rx``, ascending.
        local: ``(n,)`` int64 pixel index inside the region, ``(y % fy) * fx + x % fx``.
        t: ``(n,)`` timestamps, ascending inside each region.
        change: ``(n,)`` int8 level change of the event: +1 (ON), -1 (OFF) or 0 (a held knot
            of :func:`hold_knots`); int64 in a streaming window, whose first knot of a pixel
            carries the pixel's whole level.
    """

    region: Tensor
    local: Tensor
    t: Tensor
    change: Tensor


def region_chunks(
    events: Events,
    *,
    factor: tuple[int, int],
    out_width: int,
    size: int = CHUNK_EVENTS,
    change: Tensor | None = None,
) -> Iterator[RegionChunk]:
    """Split a stream into chunks of whole regions with about ``size`` events each.

    Regions do not interact, so the estimators process them chunk by chunk: this bounds their
    memory and keeps temporary tensors small (much faster on the CPU than tensors of hundreds
    of MB, which the allocator faults in afresh every time).

    Args:
        events: ``N >= 1`` events in stable time order.
        factor: ``(fx, fy)``.
        out_width: ``Wo``, the output sensor width.
        size: target number of events per chunk (a chunk holds at least one whole region).
        change: ``(N,)`` int8 or int64 level change of each event (default: +1 for ON, -1 for
            OFF).

    Yields:
        :class:`RegionChunk` s covering the stream, regions ascending.
    """
    if change is None:
        change = polarity_sign(events.p)
    rx, ry = region_of(events, factor)
    local = pixel_columns(events, factor, (rx, ry))
    region = ry.mul_(out_width).add_(rx)
    del rx, ry
    region, order = stable_sort_small(region, int(region.max()) + 1)
    n = region.shape[0]
    bounds = [0, n]
    if n > size:
        starts = where_true(changes(region))
        wanted = torch.arange(size, n, size, device=region.device)
        after = torch.searchsorted(starts, wanted).clamp(max=starts.shape[0] - 1)
        bounds = sorted({0, n, *take(starts, after).tolist()})
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        index = order[lo:hi]
        yield RegionChunk(region[lo:hi], take(local, index), take(events.t, index),
                          take(change, index))


def pixel_knots(
    chunk: RegionChunk, *, factor: tuple[int, int], t_start: Tensor, t_end: Tensor
) -> Knots:
    """Knots of every active pixel and breakpoints of every active region of a chunk.

    Args:
        chunk: the events of consecutive regions (see :func:`region_chunks`).
        factor: ``(fx, fy)``.
        t_start: ``()`` first timestamp of the whole stream, or ``(n,)`` that of the stream
            of each event of the chunk (a batch of recordings, see :func:`estimate`).
        t_end: ``()`` last timestamp of the whole stream, or ``(n,)`` per event as ``t_start``.

    Returns:
        The :class:`Knots`.

    Example:
        >>> ev = Events.from_columns([0, 1, 0], [0, 0, 0], [0, 5, 5], [1, 1, 1])
        >>> chunk = next(region_chunks(ev, factor=(2, 1), out_width=1))
        >>> k = pixel_knots(chunk, factor=(2, 1), t_start=ev.t[0], t_end=ev.t[-1])
        >>> k.t.tolist(), k.level.tolist(), k.breakpoint.tolist(), k.bp_t.tolist()
        ([0, 5, 0, 5], [1, 2, 0, 1], [0, 1, 0, 1], [0, 5])
    """
    region_r, t_r = chunk.region, chunk.t
    device = t_r.device
    n = t_r.shape[0]
    per_region = factor[0] * factor[1]

    # Pixel order: stable by pixel inside regions (keys relative to the chunk's first region).
    first_region = region_r[0]
    key_r = (region_r - first_region) * per_region + chunk.local
    bound = (int(region_r[n - 1] - first_region) + 1) * per_region
    key_p, to_region_time = stable_sort_small(key_r, bound)
    del key_r
    t_p = take(t_r, to_region_time)
    change_p = take(chunk.change, to_region_time).to(torch.int64)

    # Breakpoints. In region-time order every event belongs to the run of its (region, t);
    # each run is a breakpoint, and a region whose first (last) event is later (earlier) than
    # t_start (t_end) gets one more breakpoint there.
    region_start = changes(region_r)
    new_run = region_start | changes(t_r)
    first_at = where_true(region_start)
    last_at = last_of_runs(first_at, n)
    active_regions = take(region_r, first_at)
    start_r, end_r = _at(t_start, first_at), _at(t_end, last_at)  # per active region
    extra_front = take(t_r, first_at) > start_r
    extra_back = take(t_r, last_at) < end_r
    front_i, back_i = extra_front.to(torch.int64), extra_back.to(torch.int64)
    # Breakpoint of each event: count the runs, plus the extra breakpoint before a region's
    # first run and the one after the previous region's last run.
    runs = new_run.to(torch.int64)
    extra = front_i.clone()
    extra[1:] += back_i[:-1]
    runs.scatter_add_(0, first_at, extra)
    event_bp = torch.cumsum(runs, 0)
    event_bp -= 1
    del runs, extra
    region_rank = run_index(region_start)
    region_first_bp = take(event_bp, first_at) - front_i
    region_last_bp = take(event_bp, last_at) + back_i
    n_bp = int(region_last_bp[-1]) + 1
    run_at = where_true(new_run)
    bp_t = torch.empty(n_bp, dtype=t_r.dtype, device=device)
    bp_t.scatter_(0, take(event_bp, run_at), take(t_r, run_at))
    fill_at = region_first_bp[extra_front]
    bp_t.scatter_(0, fill_at, _at(start_r, where_true(extra_front)).expand(fill_at.shape))
    fill_at = region_last_bp[extra_back]
    bp_t.scatter_(0, fill_at, _at(end_r, where_true(extra_back)).expand(fill_at.shape))
    del start_r, end_r
    del run_at, new_run, region_start, first_at, last_at, fill_at
    bp_first = torch.zeros(n_bp, dtype=torch.bool, device=device)
    bp_first.scatter_(0, region_first_bp, True)
    bp_last = torch.zeros(n_bp, dtype=torch.bool, device=device)
    bp_last.scatter_(0, region_last_bp, True)

    # Level after every event; the last event of each (pixel, t) run is an event knot.
    new_pixel = changes(key_p)
    level = torch.cumsum(change_p, 0)
    # Restart the sum at each pixel: its first change also takes back the previous pixel's level.
    pixel_at = where_true(new_pixel)
    before = take(level, pixel_at[1:] - 1)  # the running sum where each pixel ends
    change_p.index_add_(0, pixel_at[1:], torch.diff(before, prepend=before.new_zeros(1)).neg_())
    torch.cumsum(change_p, 0, out=level)
    del pixel_at, before
    kidx = where_true(ends(new_pixel | changes(t_p)))
    del new_pixel, change_p
    ek_t, ek_level, ek_key = take(t_p, kidx), take(level, kidx), take(key_p, kidx)
    ek_rt = take(to_region_time, kidx)
    ek_bp = take(event_bp, ek_rt)
    del t_p, level, kidx, to_region_time, event_bp, key_p
    ke = ek_t.shape[0]
    ek_first = changes(ek_key)
    del ek_key
    ek_last = ends(ek_first)
    ek_start, ek_end = _at(t_start, ek_rt), _at(t_end, ek_rt)
    front = ek_first & (ek_t > ek_start)
    back = ek_last & (ek_t < ek_end)

    # The full knot list in pixel order: front knot before, back knot after a pixel's knots.
    # A knot moves one place for each front knot up to it and each back knot before it.
    shift = front.to(torch.int64)
    shift[1:] += back[:-1]
    pos = torch.cumsum(shift, 0)
    del shift
    pos += torch.arange(ke, device=device)
    front_at, back_at = where_true(front), where_true(back)
    front_pos, back_pos = take(pos, front_at) - 1, take(pos, back_at) + 1
    total = ke + front_at.shape[0] + back_at.shape[0]
    knot_t = torch.empty(total, dtype=t_r.dtype, device=device)
    knot_t.scatter_(0, pos, ek_t)
    knot_t.scatter_(0, front_pos, _at(ek_start, front_at).expand(front_pos.shape))
    knot_t.scatter_(0, back_pos, _at(ek_end, back_at).expand(back_pos.shape))
    del ek_start, ek_end
    knot_level = torch.empty(total, dtype=torch.int64, device=device)
    knot_level.scatter_(0, pos, ek_level)
    knot_level.scatter_(0, front_pos, 0)
    knot_level.scatter_(0, back_pos, take(ek_level, back_at))
    first = torch.zeros(total, dtype=torch.bool, device=device)
    first.scatter_(0, take(pos, where_true(ek_first & ~front)), True)
    first.scatter_(0, front_pos, True)
    breakpoint = torch.empty(total, dtype=torch.int64, device=device)
    breakpoint.scatter_(0, pos, ek_bp)
    for at, knot_pos, region_bp in ((front_at, front_pos, region_first_bp),
                                    (back_at, back_pos, region_last_bp)):
        rank = take(region_rank, take(ek_rt, at))
        breakpoint.scatter_(0, knot_pos, take(region_bp, rank))
    return Knots(
        knot_t, knot_level, first, ends(first), breakpoint, bp_t, bp_first, bp_last,
        active_regions, region_first_bp,
    )


def _at(bound: Tensor, index: Tensor) -> Tensor:
    """``bound`` itself when it is one ``()`` stream bound, else its entries at ``index``."""
    return bound if bound.ndim == 0 else take(bound, index)


def region_pixels(
    knots: Knots, sensor_size: tuple[int, int, int], factor: tuple[int, int],
    bp_rank: Tensor | None = None,
) -> Tensor | int:
    """``n_r`` per breakpoint: ``fx * fy`` if the factor divides the sensor, else ``(B,)`` int64.

    ``bp_rank``: the rank of each breakpoint's region among ``knots.regions``, when the caller
    has it.
    """
    w, h, _ = sensor_size
    if w % factor[0] == 0 and h % factor[1] == 0:
        return factor[0] * factor[1]
    per_region = region_pixel_count(knots.regions, sensor_size, factor)
    return take(per_region, run_index(knots.bp_first) if bp_rank is None else bp_rank)


def level_changes(knots: Knots) -> Tensor:
    """``(K,)`` int64 change of its pixel's level at each knot (the level itself at the first)."""
    return differences(knots.level, where_true(knots.first))


def piece_time(t0: Tensor, t1: Tensor, s: Tensor) -> Tensor:
    """Time at normalised position ``s`` in ``[0, 1]`` of the pieces ``[t0, t1]``.

    Integer times are rounded half up, ``t0 + floor(s * (t1 - t0) + 0.5)``, computed from the
    piece's start so that shifting the clock shifts the result exactly. An offset within float
    error below a half counts as the half, so that crossings exactly halfway between two ticks
    round up as they should. ``s == 1`` gives ``t1`` exactly.

    The float error, with ``u = 2**-53`` (float64's unit roundoff) and ``L = t1 - t0``: where
    a crossing is a tie, the kernels compute ``s`` from exact values (integer levels, the
    threshold's level): the linear kernel in three roundings (the level's value, a
    difference, the quotient), each at most ``u`` relative; the cubic solver stops once its
    Newton step is at most 1e-15 (``< 9 u``), and a converged step is larger than the error
    it leaves. So ``s`` is within ``16 u`` of its real value. ``L`` is exact in float64
    (spans below 2**53, :func:`check_span`); ``s * L`` and ``+ 0.5`` round once each, at most
    ``u`` of the offset (``<= L``) each. The offset is therefore within ``18 u L`` of the
    real one, and an offset that far below a half counts as the half:
    :data:`RELATIVE_ERROR` (``32 u``, with margin) of the piece, plus :data:`HALF_TOLERANCE`
    for the errors of inexact inputs on short pieces. On a piece of ``1e12`` time units the
    nudge is 0.004 ticks (a fixed 1e-12 of the piece would be a whole tick); only above
    ``2**48`` units does it reach half a tick, where float64 cannot round to the tick anyway.
    """
    span = t1 - t0
    if t0.is_floating_point():
        return torch.where(s >= 1, t1, torch.minimum(t0 + s * span, t1))
    span_f = span.to(torch.float64)
    offset = s * span_f
    offset += 0.5 + HALF_TOLERANCE
    offset += RELATIVE_ERROR * span_f
    return t0 + torch.minimum(torch.floor(offset), span_f).to(torch.int64)


def emit(region: Tensor, t: Tensor, on: Tensor, out_width: int) -> Events:
    """Output events of regions ``region`` at times ``t``, sorted by ``t`` (stable)."""
    t, order = torch.sort(t, stable=True)
    region = take(region, order)
    x, y = region_xy(region, out_width)
    return Events(x, y, t, take(on, order))


def check_span(t_start: Tensor, t_end: Tensor) -> None:
    """Refuse integer streams spanning 2**53 time units or more (``t_end >= t_start``).

    ``t_start`` and ``t_end`` are ``()`` or ``(B,)`` (each recording of a batch). The spans are
    differences of int64 values, which wrap past 2**63: since ``t_end >= t_start``, a wrapped
    span is negative, and it is measured again in Python integers for the message.

    Raises:
        ValueError: see :func:`~evdown_torch.checks.check_time_span`.
    """
    if t_start.is_floating_point():
        return
    if t_start.ndim == 0 and t_end.ndim == 0:  # one stream: in Python integers at once
        check_time_span(int(t_start), int(t_end))
        return
    span = (t_end - t_start).reshape(-1)
    wrapped = where_true(span < 0)
    if wrapped.shape[0]:
        i = int(wrapped[0])
        check_time_span(int(t_start.reshape(-1)[i if t_start.ndim else 0]),
                        int(t_end.reshape(-1)[i if t_end.ndim else 0]))
    check_time_span(0, int(span.max()))
