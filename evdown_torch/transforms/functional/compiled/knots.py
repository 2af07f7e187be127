"""The estimators' compiled window machinery: regions, knots, breakpoints, rule, times.

What :mod:`~..estimation.knots` and :mod:`~..reference` do with sorts and scatters over a
whole chunk of regions, these loops do one region at a time, in the same order and with
the same arithmetic, for a curve's compiled solver (:mod:`.linear`):

* :func:`group_by_region`: a stable counting sort of a window's events by output region;
* :func:`region_knots`: one region's breakpoints (``t_start``, each distinct event time,
  ``t_end``) and its pixels' knots in pixel order (one per distinct time at the level after
  its events, a front knot ``(t_start, 0)`` and a back knot ``(t_end, last level)`` where
  needed), as :func:`~..estimation.knots.pixel_knots` builds them;
* :func:`reference_walk`: the reference rule's ``q`` after each breakpoint, the clamp
  recurrence that :func:`~..reference.reference_index` solves in closed form;
* :func:`integer_piece_time`, :func:`float_piece_time`:
  :func:`~..estimation.knots.piece_time` for one crossing;
* :func:`chunk_ends_before`: where the eager driver's chunks of regions end, so that the
  output limit is checked where it checks it.
"""

from __future__ import annotations

import numpy as np

from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.sorting import merge_order, stable_order
from evdown_torch.transforms.functional.estimation.knots import HALF_TOLERANCE, RELATIVE_ERROR

__all__ = ["TOO_WIDE", "chunk_ends_before", "float_piece_time", "group_by_region",
           "integer_piece_time", "pack", "reference_walk", "region_knots", "unpack_change",
           "unpack_local"]

#: ``0.5 + HALF_TOLERANCE`` as the eager piece_time adds it (one Python float).
_HALF = 0.5 + HALF_TOLERANCE


#: :func:`group_by_region`'s ``outside`` when a level change or a region's pixel count does not
#: fit the 32 bits it packs them in.
TOO_WIDE = -2


@compiled_loop
def group_by_region(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, change: np.ndarray, column: np.ndarray,
    row: np.ndarray, fx: int, fy: int, out_w: int, work: tuple[np.ndarray, ...],
    by_t: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:  # pragma: no cover - compiled
    """The events by region, stably: ``(regions, first_of, packed, t, outside)``.

    ``regions``: the ``R`` regions with events, ascending; ``first_of[k]``: where region
    ``regions[k]``'s events start (``R + 1`` entries) in the returned columns, which hold the
    events in region order (time order inside a region, as given): ``packed``, each one's
    place in its region (``(y % fy) * fx + x % fx``, :func:`unpack_local`) and its level
    change (:func:`unpack_change`) in one int64 (:func:`pack`; one column to scatter instead
    of two), and its time. A region's column and row are read from the tables ``column[x]``,
    ``row[y]``; ``outside``: the first event outside them, :data:`TOO_WIDE` where a change or the
    region's pixel count does not fit 32 bits, or -1 (nothing else is computed but for -1). A
    counting sort where the region ids span a few times the events, else a stable radix
    sort (:func:`~.sorting.stable_order`): the cost follows the events, not the sensor's area.

    ``work``: four int64 columns and ``by_t`` one of ``t``'s dtype, each of at least
    ``N + 1`` elements, that the returned columns are views of (the caller's scratch
    columns, :mod:`.scratch`, so that a window's grouping takes no fresh memory).
    """
    n = x.shape[0]
    region, packed, regions, first_of = work[0][:n], work[1][:n], work[2][:n], work[3][:n + 1]
    by_t = by_t[:n]
    span = 0
    widest = fx * fy
    for i in range(n):
        if x[i] < 0 or x[i] >= column.shape[0] or y[i] < 0 or y[i] >= row.shape[0]:
            return region[:0], np.zeros(1, np.int64), region, t, i
        region[i] = row[y[i]] * out_w + column[x[i]]
        span = max(span, region[i] + 1)
        widest = max(widest, abs(change[i]) + 1)
    if widest >= 1 << 31:
        return region[:0], np.zeros(1, np.int64), region, t, TOO_WIDE
    k = 0
    if span > 4 * n + 1024:  # gathered in the stable sort's order (a radix sort)
        order = stable_order(region)
        for j in range(n):
            i = order[j]
            if j == 0 or region[i] != regions[k - 1]:
                regions[k], first_of[k] = region[i], j
                k += 1
            local = (y[i] - row[y[i]] * fy) * fx + x[i] - column[x[i]] * fx
            packed[j], by_t[j] = pack(local, change[i]), t[i]
    else:  # scattered in one pass: each region's place advances through its own run
        # (Indices read from columns are cast to unsigned: ``_numba``, "Unsigned indices".)
        place = np.zeros(span + 1, np.int64)
        for i in range(n):
            place[np.uint64(region[i] + 1)] += 1
        for r in range(span):
            if place[r + 1]:
                regions[k], first_of[k] = r, place[r]
                k += 1
            place[r + 1] += place[r]
        for i in range(n):
            r, xi, yi = np.uint64(region[i]), x[i], y[i]
            j = place[r]
            place[r] = j + 1
            local = (yi - row[np.uint64(yi)] * fy) * fx + xi - column[np.uint64(xi)] * fx
            packed[np.uint64(j)], by_t[np.uint64(j)] = pack(local, change[i]), t[i]
    first_of[k] = n
    return regions[:k], first_of[:k + 1], packed, by_t, -1


@compiled_loop
def pack(local: int, change: int) -> int:  # pragma: no cover - compiled
    """An event's place in its region (high 32 bits) and level change (low 32 bits)."""
    return (local << 32) | (change & 0xFFFFFFFF)


@compiled_loop
def unpack_local(packed: int) -> int:  # pragma: no cover - compiled
    """An event's place in its region, from :func:`group_by_region`'s ``packed``."""
    return packed >> 32


@compiled_loop
def unpack_change(packed: int) -> int:  # pragma: no cover - compiled
    """An event's level change (its sign-extended low 32 bits), from ``packed``."""
    return (packed << 32) >> 32


@compiled_loop
def region_knots(
    packed: np.ndarray, t: np.ndarray, lo: int, hi: int,
    t_start: float, t_end: float, per_region: int, bp_t: np.ndarray, event_bp: np.ndarray,
    pixel_ends: np.ndarray, by_pixel: tuple[np.ndarray, np.ndarray, np.ndarray],
    k_t: np.ndarray, k_level: np.ndarray, k_bp: np.ndarray, k_first: np.ndarray,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """The breakpoints and knots of the region whose events are ``[lo, hi)`` of the columns.

    The columns ``packed`` and ``t`` are :func:`group_by_region`'s (region order, time
    order inside a region).
    Writes the region's ``nbp`` breakpoint times into ``bp_t`` and its ``nk`` knots, in pixel
    order, into ``k_t`` (time), ``k_level`` (level), ``k_bp`` (breakpoint index) and
    ``k_first`` (a pixel's first knot). Scratch: ``event_bp`` (each event's breakpoint),
    ``pixel_ends`` (``min(per_region, 4 * m + 64) + 1`` entries for ``m`` events: where each
    pixel's events end) and ``by_pixel`` (the events' level change, time and breakpoint in
    pixel order, so that the knots are built in one pass over contiguous columns). Returns
    ``(nbp, nk)``.
    """
    m = hi - lo
    # A counting sort by pixel unless the region has far fewer events than pixels.
    counted = per_region <= 4 * m + 64
    if counted:
        pixel_ends[:per_region + 1] = 0
    nbp = 0
    if t[lo] > t_start:
        bp_t[0] = t_start
        nbp = 1
    previous = t[lo]
    for j in range(np.uint64(lo), np.uint64(hi)):
        if j == lo or t[j] != previous:
            previous = t[j]
            bp_t[np.uint64(nbp)] = previous
            nbp += 1
        event_bp[j - lo] = nbp - 1
        if counted:
            pixel_ends[np.uint64(unpack_local(packed[j]) + 1)] += 1
    if t[hi - 1] < t_end:
        bp_t[nbp] = t_end
        nbp += 1
    # The region's events by pixel (stable: time order inside a pixel).
    by_change, by_t, by_bp = by_pixel
    pixels = 0
    if counted:
        for p in range(per_region):
            pixel_ends[p + 1] += pixel_ends[p]
        for j in range(np.uint64(lo), np.uint64(hi)):
            p = np.uint64(unpack_local(packed[j]))
            d = np.uint64(pixel_ends[p])
            pixel_ends[p] = d + 1
            by_change[d], by_t[d], by_bp[d] = unpack_change(packed[j]), t[j], event_bp[j - lo]
        pixels = per_region  # pixel_ends[p]: where pixel p's events end (some have none)
    else:
        by_local = merge_order(packed[lo:hi] >> 32)
        for d in range(m):
            j = np.uint64(lo + by_local[d])
            by_change[d], by_t[d], by_bp[d] = unpack_change(packed[j]), t[j], event_bp[j - lo]
            if d + 1 == m or (unpack_local(packed[lo + by_local[d + 1]])
                              != unpack_local(packed[j])):
                pixel_ends[pixels] = d + 1
                pixels += 1
    # One knot per (pixel, t), after all its events; a front and a back knot where needed.
    nk = 0
    begin = 0
    for p in range(pixels):
        end = pixel_ends[p]
        if end == begin:
            continue
        level = 0
        pixel_first = nk
        for j in range(np.uint64(begin), np.uint64(end)):
            level += by_change[j]
            te = by_t[j]
            if j + 1 < end and by_t[j + 1] == te:
                continue
            if nk == pixel_first and te > t_start:
                k_t[nk], k_level[nk], k_bp[nk], k_first[nk] = t_start, 0, 0, True
                nk += 1
            k_t[nk], k_level[nk], k_bp[nk] = te, level, by_bp[j]
            k_first[nk] = nk == pixel_first
            nk += 1
        if k_t[nk - 1] < t_end:
            k_t[nk], k_level[nk], k_bp[nk], k_first[nk] = t_end, level, nbp - 1, False
            nk += 1
        begin = end
    return nbp, nk


@compiled_loop
def reference_walk(floor_u: np.ndarray, on_level: np.ndarray, nbp: int, q_start: int,
                   q_after: np.ndarray) -> int:  # pragma: no cover - compiled
    """The reference index after each of ``nbp`` moves into ``q_after``; the levels crossed.

    On a level ``q`` is that level; strictly inside cell ``(m, m + 1)`` it is ``q`` clamped
    to ``[m, m + 1]``.
    """
    q = q_start
    crossed = 0
    for i in range(nbp):
        m = floor_u[i]
        before = q
        q = m if on_level[i] else min(max(q, m), m + 1)
        crossed += abs(q - before)
        q_after[i] = q
    return crossed


@compiled_loop
def integer_piece_time(t0: int, t1: int, s: float) -> int:  # pragma: no cover - compiled
    """The integer time at position ``s`` of ``[t0, t1]``, rounded half up from ``t0``.

    As :func:`~..estimation.knots.piece_time` computes it, with its tolerances.
    """
    span = float(t1 - t0)
    offset = s * span
    offset += _HALF
    offset += RELATIVE_ERROR * span
    return t0 + np.int64(min(np.floor(offset), span))


@compiled_loop
def float_piece_time(t0: float, t1: float, s: float) -> float:  # pragma: no cover - compiled
    """The float time at normalised position ``s`` of the piece ``[t0, t1]``."""
    if s >= 1.0:
        return t1
    return min(t0 + s * (t1 - t0), t1)


@compiled_loop
def chunk_ends_before(lo: int, previous_start: int, last: bool, n: int,
                      chunk_events: int) -> bool:  # pragma: no cover - compiled
    """Whether the eager driver's chunk of regions ends before a region starting at ``lo``.

    Its chunks end before the first region that starts at or after each multiple of
    ``chunk_events`` below ``n`` (the last region for a multiple past every start);
    ``previous_start``: where the region before starts.
    """
    bound = n - 1 if last else lo
    return bound // chunk_events > previous_start // chunk_events
