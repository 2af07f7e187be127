"""LinearEstimation's compiled window: the knots, the breakpoints and the solver in one loop.

The eager driver (:func:`~..estimation.driver.estimate_window`) groups a window's knot events
by region and by pixel with sorts, builds the knots and breakpoints of every region
(:func:`~..estimation.knots.pixel_knots`) and hands them to the linear solver
(:func:`~..estimation.linear.linear_regions`). This loop takes the window's events in time
order and does the same region by region: a counting sort by region and, inside a region,
by pixel, then the knots, the slopes, the region's sums along its breakpoints, the reference
rule and the crossing times.

Every float is computed as the eager kernels compute it, in the same order: each slope as
``rise / run``; the region's fixed-point scale from its steepest slope; the slope sums'
high parts in int64 and low parts added at each breakpoint in pixel order (as
``index_add_`` adds them), then summed along the breakpoints from 0.0 (as ``cumsum`` does);
the pixels' progress as the running sum of ``slope_sum * gap - whole_change``; the level
test of :func:`~..reference.level_index` and the crossing times of
:func:`~..estimation.knots.piece_time`. So both paths give the same events, bit for bit
(``tests/transforms/test_compiled_estimation.py``). The reference rule is the clamp
recurrence that :func:`~..reference.reference_index` solves in closed form.

The output limit is applied as the eager driver applies it: its count is checked after each
of the driver's chunks of regions (:data:`~..estimation.driver.REGION_CHUNK_EVENTS` events),
so an output over the limit raises the same error with the same count.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import torch
from torch import Tensor

from evdown_torch.checks import check_output_count, output_limit
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.knots import (
    chunk_ends_before,
    float_piece_time,
    group_by_region,
    integer_piece_time,
    reference_walk,
    region_knots,
)
from evdown_torch.transforms.functional.compiled.regions import (
    columns_of,
    outside_error,
    region_tables,
)
from evdown_torch.transforms.functional.reference import SNAP

__all__ = ["linear_window"]

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
    """``column``'s first ``kept`` values in a new array of ``capacity``."""
    grown = np.empty(capacity, column.dtype)
    grown[:kept] = column[:kept]
    return grown


@compiled_loop
def _linear_loop(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, change: np.ndarray,
    start_of: np.ndarray, end_of: np.ndarray, fx: int, fy: int, out_w: int, out_h: int,
    width: int, height: int, a: int, b: int, level_scale: float, divides: bool,
    integer_time: bool, q: np.ndarray, has_cut: bool, cut: np.ndarray, has_next: bool,
    next_cut: np.ndarray, limit: int, chunk_events: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:  # pragma: no cover - compiled
    """The crossings of every region of a window, in region order; ``q`` moved to ``next_cut``.

    Returns ``(region, t, on, over)``: ``over`` is -1, or the count the eager driver would
    report when the output exceeds ``limit`` (the crossings are then not all written), or
    ``-2 - i`` for an event ``i`` outside the sensor (nothing done).
    """
    n = t.shape[0]
    per_region = fx * fy
    local, first_of, order, outside = group_by_region(x, y, fx, fy, out_w,
                                                      start_of.shape[0] * out_h)
    if outside >= 0:
        return np.empty(0, np.int64), np.empty(0, t.dtype), np.empty(0, np.bool_), -2 - outside
    # Scratch for one region: at most its events, plus a front and a back knot per pixel.
    event_bp, by_pixel = np.empty(n, np.int64), np.empty(n, np.int64)
    pixel_count = np.zeros(per_region + 1, np.int64)
    bp_t = np.empty(n + 2, t.dtype)
    high_bp, count_bp, whole = np.empty(n + 2, np.int64), np.empty(n + 2, np.int64), np.empty(
        n + 2, np.int64)
    low_bp, part = np.empty(n + 2, np.float64), np.empty(n + 2, np.float64)
    floor_u, q_after = np.empty(n + 2, np.int64), np.empty(n + 2, np.int64)
    on_level = np.empty(n + 2, np.bool_)
    k_t, k_level, k_bp = np.empty(3 * n, t.dtype), np.empty(3 * n, np.int64), np.empty(
        3 * n, np.int64)
    k_first, slope = np.empty(3 * n, np.bool_), np.empty(3 * n, np.float64)

    capacity = max(16, n)
    out_region = np.empty(capacity, np.int64)
    out_t = np.empty(capacity, t.dtype)
    out_on = np.empty(capacity, np.bool_)
    written = 0
    total = 0  # crossings counted so far (written while within the limit)
    previous_start = -1
    n_regions = first_of.shape[0] - 1
    last_region = n_regions - 1
    while first_of[last_region] == first_of[last_region + 1]:
        last_region -= 1
    for r in range(n_regions):
        lo, hi = first_of[r], first_of[r + 1]
        if lo == hi:
            continue
        if previous_start >= 0 and limit >= 0 and total > limit and chunk_ends_before(
                lo, previous_start, r == last_region, n, chunk_events):
            return out_region[:0], out_t[:0], out_on[:0], total
        previous_start = lo
        t_start, t_end = start_of[r // (out_w * out_h)], end_of[r // (out_w * out_h)]
        nbp, nk = region_knots(order, local, t, change, lo, hi, t_start, t_end, per_region,
                               bp_t, event_bp, by_pixel, pixel_count, k_t, k_level, k_bp,
                               k_first)
        rx, ry = r % out_w, (r // out_w) % out_h
        pixels = min(width - rx * fx, fx) * min(height - ry * fy, fy)
        _linear_sums(k_t, k_level, k_bp, k_first, nk, bp_t, nbp, per_region, slope, high_bp,
                     low_bp, count_bp, whole, part)
        for i in range(nbp):
            floor_u[i], on_level[i] = _level_index(whole[i], part[i], pixels, a, b,
                                                   level_scale, divides)
        if has_cut:  # a resumed window: breakpoints before the cut take the cut's value
            done = 0
            while done < nbp and bp_t[done] < cut[0]:
                done += 1
            for i in range(done - 1):
                floor_u[i], on_level[i] = floor_u[done - 1], on_level[done - 1]
        q_start = q[r] if q.shape[0] else 0
        crossed = reference_walk(floor_u, on_level, nbp, q_start, q_after)
        total += crossed
        if has_next:  # q after the region's last breakpoint before the next cut
            for i in range(nbp - 1, -1, -1):
                if bp_t[i] < next_cut[0]:
                    q[r] = q_after[i]
                    break
        if crossed == 0 or (limit >= 0 and total > limit):
            continue
        if written + crossed > capacity:
            capacity = max(2 * capacity, written + crossed)
            out_region = _grown(out_region, written, capacity)
            out_t = _grown(out_t, written, capacity)
            out_on = _grown(out_on, written, capacity)
        for i in range(nbp):
            q_before = q_after[i - 1] if i else q_start
            delta = q_after[i] - q_before
            begin = i - 1 if i else i  # the piece ending at i; a jump at the first
            whole_begin, part_begin = float(whole[begin]), part[begin]
            rise = float(whole[i] - whole[begin])
            for step in range(abs(delta)):
                level = q_before + 1 + step if delta > 0 else q_before - 1 - step
                s = 1.0
                if i and not (on_level[i] and level == floor_u[i]):
                    target = float(level * pixels * a) / float(b)
                    s = ((target - whole_begin) - part_begin) / (rise + (part[i] - part_begin))
                    s = 0.0 if np.isnan(s) else min(max(s, 0.0), 1.0)
                if integer_time:
                    out_t[written] = integer_piece_time(bp_t[begin], bp_t[i], s)
                else:
                    out_t[written] = float_piece_time(bp_t[begin], bp_t[i], s)
                out_region[written] = r
                out_on[written] = delta > 0
                written += 1
    if limit >= 0 and total > limit:
        return out_region[:0], out_t[:0], out_on[:0], total
    return out_region[:written], out_t[:written], out_on[:written], -1


@compiled_loop
def _linear_sums(
    k_t: np.ndarray, k_level: np.ndarray, k_bp: np.ndarray, k_first: np.ndarray, nk: int,
    bp_t: np.ndarray, nbp: int, per_region: int, slope: np.ndarray, high_bp: np.ndarray,
    low_bp: np.ndarray, count_bp: np.ndarray, whole: np.ndarray, part: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """One region's ``n_r * M_r`` at its breakpoints: the exact ``whole`` and the ``part``.

    As :func:`~..estimation.linear.linear_regions` computes them: each knot's slope to the
    next (0 at a pixel's last), the region's fixed-point scale from its steepest slope, the
    slope sum's changes per breakpoint (high parts in int64, low parts added in pixel order),
    then along the breakpoints the slope sum, the integer levels and the pixels' progress,
    restarted where every pixel has a knot.
    """
    steepest = 0.0
    for k in range(nk):
        if k + 1 < nk and not k_first[k + 1]:
            slope[k] = float(k_level[k + 1] - k_level[k]) / float(k_t[k + 1] - k_t[k])
        else:
            slope[k] = 0.0
        steepest = max(steepest, abs(slope[k]))
    scale = 1.0
    if steepest != 0.0:
        scale = math.ldexp(1.0, 60 - math.frexp(steepest * per_region)[1])
    high_bp[:nbp] = 0
    low_bp[:nbp] = 0.0
    count_bp[:nbp] = 0
    whole[:nbp] = 0
    high_previous, low_previous, level_previous = 0, 0.0, 0
    for k in range(nk):
        high_f = np.rint(slope[k] * scale)
        low = slope[k] - high_f / scale
        high = np.int64(high_f)
        i = k_bp[k]
        if k_first[k]:
            high_previous, low_previous, level_previous = 0, 0.0, 0
            high_bp[i] += high
            low_bp[i] += low
        else:
            high_bp[i] += high - high_previous
            low_bp[i] += low - low_previous
        whole[i] += k_level[k] - level_previous
        count_bp[i] += 1
        high_previous, low_previous, level_previous = high, low, k_level[k]
    high_sum, low_sum, slope_sum, running, idle_total = 0, 0.0, 0.0, 0.0, 0.0
    for i in range(nbp):
        high_sum += high_bp[i]
        low_sum += low_bp[i]
        step = 0.0
        if i:
            whole[i] += whole[i - 1]
            step = slope_sum * float(bp_t[i] - bp_t[i - 1]) - float(whole[i] - whole[i - 1])
        slope_sum = float(high_sum) / scale + low_sum
        running += step
        if count_bp[i] == count_bp[0]:
            idle_total = running
        part[i] = running - idle_total


def linear_window(
    events_x: Tensor, events_y: Tensor, events_t: Tensor, change: Tensor, *,
    t_start: Tensor, t_end: Tensor, sensor_size: tuple[int, int, int],
    factor: tuple[int, int], out_size: tuple[int, int], fraction: Fraction,
    resume_cut: Tensor | None, resume_q: Tensor | None, next_cut: Tensor | None,
    chunk_events: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
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
        next_cut: ``()`` next cut (with ``resume_q``), or ``None``.
        chunk_events: the eager driver's events per chunk of regions (its limit checks).

    Returns:
        ``(region, t, on, q)``: the crossings' ``(C,)`` int64 regions, times (the events'
        dtype) and polarities in region order, and with ``next_cut`` the ``(Wo * Ho,)``
        int64 reference index after each region's last breakpoint earlier than it.

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
    has_cut = resume_cut is not None
    has_next = next_cut is not None and resume_q is not None
    cut = np.zeros(1, t.dtype) if resume_cut is None else resume_cut.reshape(1).numpy()
    after = np.zeros(1, t.dtype) if next_cut is None else next_cut.reshape(1).numpy()
    limit = output_limit()
    region, out_t, on, over = _linear_loop(
        x, y, t, change_np, start_of, end_of, fx, fy, out_size[0], out_size[1], width, height,
        a, b, b / (fx * fy * a), divides, not t_dtype.is_floating_point, q, has_cut, cut,
        has_next, after, -1 if limit is None else limit, chunk_events,
    )
    if over <= -2:
        column, row = region_tables(factor, out_size[0], start_of.shape[0] * out_size[1])
        raise outside_error(-2 - over, x, y, column, row)
    if over >= 0:
        check_output_count(over)
    return (torch.from_numpy(region), torch.from_numpy(out_t), torch.from_numpy(on),
            torch.from_numpy(q) if has_next else None)
