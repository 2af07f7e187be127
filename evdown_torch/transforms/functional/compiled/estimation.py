"""The estimators' compiled window: knots, breakpoints, a curve's solver and the rule, per region.

The eager driver (:func:`~..estimation.driver.estimate_window`) groups a window's knot events
by region and by pixel with sorts, builds the knots and breakpoints of every region
(:func:`~..estimation.knots.pixel_knots`) and hands them to its curve's solver
(:func:`~..estimation.linear.linear_regions`, :func:`~..estimation.cubic.cubic_regions`).
:func:`estimation_window` takes the window's events in time order and does the same region
by region in one loop: a counting sort by region and, inside a region, by pixel
(:mod:`.knots`), the curve's sums at the breakpoints and its monotone moves (:mod:`.linear`,
:mod:`.cubic`), the level test of :func:`~..reference.level_index`, the reference rule
(the clamp recurrence that :func:`~..reference.reference_index` solves in closed form) and
the crossing times of :func:`~..estimation.knots.piece_time`. Every float is computed as the
eager kernels compute it, in the same order, so both paths give the same events, bit for bit
(``tests/transforms/test_compiled_estimation.py``).

The output limit is applied as the eager driver applies it: its count is checked after each
of the driver's chunks of regions (:data:`~..estimation.driver.REGION_CHUNK_EVENTS` events),
so an output over the limit raises the same error with the same count.
"""

from __future__ import annotations

import functools
from fractions import Fraction
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evdown_torch.checks import check_output_count, output_limit
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.cubic import (
    addcmul_is_fused,
    monotone_moves,
    pchip_slopes,
    region_sums,
    solve,
)
from evdown_torch.transforms.functional.compiled.knots import (
    TOO_WIDE,
    chunk_ends_before,
    float_piece_time,
    group_by_region,
    integer_piece_time,
    reference_walk,
    region_knots,
)
from evdown_torch.transforms.functional.compiled.linear import linear_position, linear_sums
from evdown_torch.transforms.functional.compiled.regions import (
    columns_of,
    outside_error,
    region_tables,
)
from evdown_torch.transforms.functional.compiled.scratch import scratch_column
from evdown_torch.transforms.functional.reference import SNAP

__all__ = ["estimation_window"]


@compiled_loop
def _level_index(whole: int, part: float, pixels: int, a: int, b: int, scale: float,
                 divides: bool) -> tuple[int, bool]:  # pragma: no cover - compiled
    """``level_index`` of one breakpoint: ``(floor(u), u on a level)``."""
    if part == 0.0:
        numerator = whole * b
        denominator = pixels * a
        exact = numerator // denominator
        return exact, exact * denominator == numerator
    if divides:
        u = (float(whole) + part) * scale
    else:
        u = (float(whole) + part) * float(b) / float(pixels * a)
    nearest = np.rint(u)
    if abs(u - nearest) <= SNAP:
        return np.int64(nearest), True
    return np.int64(np.floor(u)), False


@compiled_loop
def _grown(column: np.ndarray, kept: int, capacity: int) -> np.ndarray:  # pragma: no cover
    """``column``'s first ``kept`` values in a new array of ``capacity``.

    A loop, not a slice assignment: Numba compiles the slice's shape check with its error
    message's formatting, about 3 s of the window loop's first compile.
    """
    grown = np.empty(capacity, column.dtype)
    for i in range(kept):
        grown[i] = column[i]
    return grown


#: The window loop's ``over`` for a window it leaves to the eager driver: a level change
#: (a pixel's whole level, carried by a session's first knot of it) of 2**31 or more.
TOO_WIDE_CALL = -(1 << 62)


@functools.cache
def _window_loop_of(cubic: bool) -> Any:
    """The window loop of one curve, compiled on its first call (the loop below).

    ``cubic`` is a constant of the loop's closure: Numba drops the other curve's branches
    before typing them, so a LinearEstimation's first call compiles none of the cubic
    pieces (3 to 4 s of its cold first call, docs/benchmarks.md) and a CubicEstimation's
    none of the linear ones. Numba's disk cache keys each loop by its closure's values,
    and each loop has a name of its own (below).
    """

    def window_loop(
        x: np.ndarray, y: np.ndarray, t: np.ndarray, change: np.ndarray, column: np.ndarray,
        row: np.ndarray, start_of: np.ndarray, end_of: np.ndarray, fx: int, fy: int, out_w: int,
        out_h: int,
        width: int, height: int, a: int, b: int, level_scale: float, divides: bool,
        integer_time: bool, front_at_rest: bool, fused: bool, q: np.ndarray,
        returned: np.ndarray, has_cut: bool, cut: np.ndarray, has_next: bool,
        next_cut: np.ndarray, limit: int,
        chunk_events: int, work: tuple[np.ndarray, ...], work_t: tuple[np.ndarray, ...],
        work_on: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:  # pragma: no cover - compiled
        """A window's crossings to return, in region order; ``q``, ``returned`` at ``next_cut``.

        Of a resumed window, the crossings not returned before (``resumed_crossings``: the
        first ``returned[r]`` of the piece that crosses the cut dropped, the rest no earlier
        than the cut), up to each region's first at or after ``next_cut``.

        Returns ``(region, t, on, over)``: ``over`` is -1, or the count the eager driver would
        report when the output exceeds ``limit`` (the crossings are then not all written),
        ``-2 - i`` for an event ``i`` outside the sensor, or :data:`TOO_WIDE_CALL` for a level
        change of 2**31 or more (nothing done for either).

        ``work`` (five int64 columns), ``work_t`` (two of ``t``'s dtype) and ``work_on`` (bool),
        each of at least ``N + 1`` elements: the grouping's columns and the outputs (as many
        crossings as ``work_on`` holds), which are views of them unless the crossings outgrow
        them.
        """
        n = t.shape[0]
        per_region = fx * fy
        regions, first_of, packed, t, outside = group_by_region(x, y, t, change, column, row, fx,
                                                                fy, out_w, work[:4], work_t[0])
        if outside != -1:  # an event outside the sensor, or a change too wide to pack
            code = TOO_WIDE_CALL if outside == TOO_WIDE else -2 - outside
            return np.empty(0, np.int64), np.empty(0, t.dtype), np.empty(0, np.bool_), code
        # Scratch for one region, sized by the largest (small arrays, reused while in cache): at
        # most its events plus a front and a back knot per pixel; its breakpoints, and up to
        # three monotone moves per breakpoint.
        m = 0
        for k in range(regions.shape[0]):
            m = max(m, first_of[k + 1] - first_of[k])
        event_bp = np.empty(m, np.int64)
        pixel_ends = np.zeros(min(per_region, 4 * m + 64) + 1, np.int64)  # see region_knots
        by_pixel = np.empty(m, np.int64), np.empty(m, t.dtype), np.empty(m, np.int64)
        k_t, k_level = np.empty(3 * m, t.dtype), np.empty(3 * m, np.int64)
        k_bp, k_first = np.empty(3 * m, np.int64), np.empty(3 * m, np.bool_)
        slope, k_width, k_rise = (np.empty(3 * m, np.float64), np.empty(3 * m, np.float64),
                                  np.empty(3 * m, np.float64))
        bp_t = np.empty(m + 2, t.dtype)
        high_bp, count_bp, whole = (np.empty(m + 2, np.int64), np.empty(m + 2, np.int64),
                                    np.empty(m + 2, np.int64))
        low_bp, part, derivative = (np.empty(m + 2, np.float64), np.empty(m + 2, np.float64),
                                    np.empty(m + 2, np.float64))
        c1, c2, c3 = (np.empty(m + 2, np.float64), np.empty(m + 2, np.float64),
                      np.empty(m + 2, np.float64))
        moves = 3 * (m + 2) if cubic else m + 2
        move_bp, move_whole = np.empty(moves, np.int64), np.empty(moves, np.int64)
        move_s, move_part = np.empty(moves, np.float64), np.empty(moves, np.float64)
        floor_u, q_after = np.empty(moves, np.int64), np.empty(moves, np.int64)
        on_level = np.empty(moves, np.bool_)

        capacity = work_on.shape[0]
        out_region, out_t, out_on = work[4][:capacity], work_t[1][:capacity], work_on
        written = np.int64(0)  # (np.int64: a literal 0 would compile _grown twice)
        total = 0  # crossings counted so far (written while within the limit)
        previous_start = np.int64(-1)  # (likewise chunk_ends_before)
        origin = start_of[0]  # the eager chunk's first knot time (its cubic sums' origin)
        n_regions = regions.shape[0]
        for k in range(n_regions):
            r, lo, hi = regions[k], first_of[k], first_of[k + 1]
            rec = r // (out_w * out_h)
            if previous_start < 0 or chunk_ends_before(lo, previous_start, k == n_regions - 1, n,
                                                       chunk_events):
                if limit >= 0 and total > limit:
                    return out_region[:0], out_t[:0], out_on[:0], total
                origin = start_of[rec]
            previous_start = lo
            nbp, nk = region_knots(packed, t, lo, hi, start_of[rec], end_of[rec], per_region,
                                   bp_t, event_bp, pixel_ends, by_pixel, k_t, k_level, k_bp,
                                   k_first)
            rx, ry = r % out_w, (r // out_w) % out_h
            pixels = min(width - rx * fx, fx) * min(height - ry * fy, fy)
            if cubic:
                pchip_slopes(k_t, k_level, k_first, nk, front_at_rest, slope, k_width, k_rise)
                _breakpoint_levels(k_level, k_bp, k_first, nk, nbp, whole)
                region_sums(k_t, k_bp, k_first, nk, slope, k_width, k_rise, bp_t, nbp,
                            integer_time, origin, fused, part, derivative)
                n_moves = monotone_moves(bp_t, nbp, whole, part, derivative, fused, c1, c2, c3,
                                         move_bp, move_s, move_whole, move_part)
                for e in range(n_moves):
                    floor_u[e], on_level[e] = _level_index(move_whole[e], move_part[e], pixels, a,
                                                           b, level_scale, divides)
            else:  # a move at each breakpoint, to its end
                linear_sums(k_t, k_level, k_bp, k_first, nk, bp_t, nbp, per_region, slope, high_bp,
                            low_bp, count_bp, whole, part)
                n_moves = nbp
                for e in range(nbp):
                    move_bp[e], move_s[e] = e, 1.0
                    floor_u[e], on_level[e] = _level_index(whole[e], part[e], pixels, a, b,
                                                           level_scale, divides)
            # The region's breakpoints before the cut and before the next cut.
            n_cut = 0
            while has_cut and n_cut < nbp and bp_t[n_cut] < cut[0]:
                n_cut += 1
            n_next = 0
            while has_next and n_next < nbp and bp_t[n_next] < next_cut[0]:
                n_next += 1
            if has_cut:  # a resumed window: the moves before the cut take the cut's value
                done = 0
                while done < n_moves and move_bp[done] < n_cut:
                    done += 1
                for e in range(done - 1):
                    floor_u[e], on_level[e] = floor_u[done - 1], on_level[done - 1]
            q_start = q[r] if q.shape[0] else 0
            crossed = reference_walk(floor_u, on_level, n_moves, q_start, q_after)
            total += crossed
            # The crossings of the piece that crosses the cut returned before, and of the one
            # that crosses the next cut returned so far.
            old = returned[r] if n_cut > 0 else 0
            count = old if n_next > 0 and n_next == n_cut else 0
            if has_next:  # q after the region's last move ending before the next cut
                for e in range(n_moves - 1, -1, -1):
                    if move_bp[e] < n_next:
                        q[r] = q_after[e]
                        break
            if crossed == 0 or (limit >= 0 and total > limit):
                if has_next:
                    returned[r] = count
                continue
            if written + crossed > capacity:
                capacity = max(2 * capacity, written + crossed)
                out_region = _grown(out_region, written, capacity)
                out_t = _grown(out_t, written, capacity)
                out_on = _grown(out_on, written, capacity)
            late = False  # a crossing at or after the next cut: the region's rest waits
            for e in range(n_moves):
                q_before = q_after[e - 1] if e else q_start
                delta = q_after[e] - q_before
                i = move_bp[e]
                if i < n_cut or late:  # a piece that ends before the cut: returned before
                    continue
                begin = i - 1 if i else i  # the piece ending at i; a jump at the first
                s_low = move_s[e - 1] if e and move_bp[e - 1] == i else 0.0
                for step in range(abs(delta)):
                    if n_cut > 0 and i == n_cut and old > 0:  # returned before
                        old -= 1
                        continue
                    level = q_before + 1 + step if delta > 0 else q_before - 1 - step
                    s = move_s[e]
                    if i and not (on_level[e] and level == floor_u[e]):
                        target = float(level * pixels * a) / float(b)
                        if cubic:
                            goal = target - float(whole[begin])
                            goal -= part[begin]
                            s = solve(c1[i], c2[i], c3[i], goal, s_low, s, delta > 0)
                        else:
                            s = linear_position(target, whole[begin], part[begin], whole[i],
                                                part[i])
                    # (written, then read: one variable for both would be typed float64)
                    if integer_time:
                        out_t[written] = integer_piece_time(bp_t[begin], bp_t[i], s)
                    else:
                        out_t[written] = float_piece_time(bp_t[begin], bp_t[i], s)
                    if n_cut > 0 and i == n_cut and out_t[written] < cut[0]:
                        out_t[written] = cut[0]
                    if has_next and out_t[written] >= next_cut[0]:
                        late = True
                        break
                    if i == n_next and n_next > 0:
                        count += 1
                    out_region[written] = r
                    out_on[written] = delta > 0
                    written += 1
            if has_next:
                returned[r] = count
        if limit >= 0 and total > limit:
            return out_region[:0], out_t[:0], out_on[:0], total
        return out_region[:written], out_t[:written], out_on[:written], -1

    # A name of its own for each curve's loop: Numba names a compiled function's symbols after
    # its qualified name and a counter of its process, so both loops, compiled in two
    # processes under one name, got the same symbols, and a process that loaded both from the
    # disk cache failed on the second ("NRT_adapt_ndarray_to_python: descr is NULL"). Their
    # cache files are apart too.
    window_loop.__name__ = f"window_loop_{'cubic' if cubic else 'linear'}"
    window_loop.__qualname__ = f"_window_loop_of.<locals>.{window_loop.__name__}"
    return compiled_loop(window_loop)


@compiled_loop
def _breakpoint_levels(k_level: np.ndarray, k_bp: np.ndarray, k_first: np.ndarray, nk: int,
                       nbp: int, whole: np.ndarray) -> None:  # pragma: no cover - compiled
    """The exact integer part of ``n_r * M_r`` at each breakpoint (``breakpoint_levels``)."""
    whole[:nbp] = 0
    for k in range(nk):
        whole[k_bp[k]] += k_level[k] - (0 if k_first[k] else k_level[k - 1])
    for i in range(1, nbp):
        whole[i] += whole[i - 1]


def estimation_window(
    events_x: Tensor, events_y: Tensor, events_t: Tensor, change: Tensor, *,
    t_start: Tensor, t_end: Tensor, sensor_size: tuple[int, int, int],
    factor: tuple[int, int], out_size: tuple[int, int], fraction: Fraction,
    resume_cut: Tensor | None, resume_q: Tensor | None, resume_returned: Tensor | None,
    next_cut: Tensor | None, chunk_events: int, cubic: bool, front_at_rest: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None] | None:
    """The crossings of a window, as the eager driver's chunks of regions find them.

    Args:
        events_x: ``(N,)`` int64 columns of ``N >= 1`` knot events in stable time order.
        events_y: ``(N,)`` int64 rows (a batch's recordings stacked vertically).
        events_t: ``(N,)`` int64 or float64 times, within each recording's span.
        change: ``(N,)`` int64 level change of each event.
        t_start: ``()`` first timestamp of the stream, or ``(B,)`` of each recording.
        t_end: ``()`` last timestamp (the back knots), or ``(B,)``.
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        out_size: ``(Wo, Ho)``.
        fraction: the (capped) threshold ``a / b``.
        resume_cut: ``()`` cut of a resumed window, or ``None``.
        resume_q: ``(Wo * Ho,)`` int64 reference index of each region at the cut, or
            ``None`` (a window from ``t_start``, every region at 0).
        resume_returned: ``(Wo * Ho,)`` int64 count of each region's crossings after the
            cut's breakpoint returned already (with ``resume_q``).
        next_cut: ``()`` next cut (with ``resume_q``), or ``None``.
        chunk_events: the eager driver's events per chunk of regions (its limit checks).
        cubic: the cubic curve (PCHIP; needs :func:`~.cubic.addcmul_is_fused` not ``None``),
            else the linear one.
        front_at_rest: a bounded delay: each pixel's cubic slope at its first knot is 0.

    Returns:
        ``(region, t, on, q, returned)``: the crossings' ``(C,)`` int64 regions, times (the
        events' dtype) and polarities in region order (views of this thread's scratch columns,
        :func:`~.scratch.scratch_column`, while the output fits them), and with ``next_cut``
        the ``(Wo * Ho,)`` int64 reference index after each region's last breakpoint earlier
        than it and the count of its crossings since that are returned (else ``None``, twice);
        ``None`` for a window with a level change of 2**31 or more (a pixel's whole
        level, carried by a session's first knot of it), which the loop does not pack: the
        eager driver's.

    Raises:
        OutputLimitError: as the eager driver raises it, with the same count.
        ValueError: for an event outside the sensor (never a read out of bounds).
    """
    width, height, _ = sensor_size
    fx, fy = factor
    a, b = fraction.numerator, fraction.denominator
    divides = width % fx == 0 and height % fy == 0
    t_dtype = events_t.dtype
    x, y, t, change_np = columns_of(events_x, events_y, events_t, change.to(torch.int64))
    start_of = np.ascontiguousarray(t_start.reshape(-1).numpy())
    end_of = np.ascontiguousarray(t_end.reshape(-1).numpy())
    q = np.zeros(0, np.int64) if resume_q is None else resume_q.numpy().copy()
    returned = (np.zeros(0, np.int64) if resume_returned is None
                else resume_returned.numpy().copy())
    has_cut = resume_cut is not None
    has_next = next_cut is not None and resume_q is not None
    cut = np.zeros(1, t.dtype) if resume_cut is None else resume_cut.reshape(1).numpy()
    after = np.zeros(1, t.dtype) if next_cut is None else next_cut.reshape(1).numpy()
    limit = output_limit()
    fused = bool(addcmul_is_fused()) if cubic else False
    column, row = region_tables(factor, out_size[0], start_of.shape[0] * out_size[1])
    size = max(x.shape[0], 16) + 1  # the grouping's N + 1, and room for 16 crossings at least
    work = tuple(scratch_column(f"window {i}", size, np.int64) for i in range(5))
    work_t = tuple(scratch_column(f"window t {i}", size, t.dtype) for i in range(2))
    region, out_t, on, over = _window_loop_of(cubic)(
        x, y, t, change_np, column, row, start_of, end_of, fx, fy, out_size[0], out_size[1],
        width, height, a, b, b / (fx * fy * a), divides, not t_dtype.is_floating_point,
        front_at_rest, fused, q, returned, has_cut, cut, has_next, after,
        -1 if limit is None else limit, chunk_events, work, work_t,
        scratch_column("window on", size, np.bool_),
    )
    if over == TOO_WIDE_CALL:
        return None
    if over <= -2:
        raise outside_error(-2 - over, x, y, column, row)
    if over >= 0:
        check_output_count(over)
    return (torch.from_numpy(region), torch.from_numpy(out_t), torch.from_numpy(on),
            torch.from_numpy(q) if has_next else None,
            torch.from_numpy(returned) if has_next else None)
