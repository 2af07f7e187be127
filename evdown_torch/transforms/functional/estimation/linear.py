"""Linear log-luminance estimation kernel: exact crossings of the regions' mean polylines."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import differences, last_of_runs, run_index, take, where_true
from evdown_torch.transforms.functional.estimation.knots import Knots, piece_time, region_pixels
from evdown_torch.transforms.functional.estimation.solver import (
    CurveCrossings,
    RegionJob,
    breakpoint_levels,
    resume_moves,
)
from evdown_torch.transforms.functional.reference import level_index, level_value, move_crossings

__all__ = ["linear_regions", "local_cumsum", "rows_cumsum",
           "segment_rows", "SegmentRows"]


def local_cumsum(values: Tensor, first_at: Tensor) -> Tensor:
    """Float cumulative sums restarting at each segment, each bit for bit as if alone.

    A cumulative sum over many segments minus its value before each segment (as
    :func:`~evdown_torch._tensors.segmented_cumsum` does) carries the rounding of the segments
    before into each segment's last bits, so a region's result would depend on the regions
    processed with it (a batch of recordings, a chunk of regions). Here each segment is one
    row of a ``(segments, width)`` tensor summed along its rows from 0 (the rows of
    :func:`segment_rows`, which several sums over the same segments can share).

    Args:
        values: ``(N,)`` float64.
        first_at: ``(S,)`` int64 start of each segment, ascending, the first 0.

    Returns:
        ``(N,)`` float64 sums.

    Example:
        >>> local_cumsum(torch.tensor([1.0, 2.0, 4.0, 8.0, 16.0]), torch.tensor([0, 2, 3])).tolist()
        [1.0, 3.0, 4.0, 8.0, 24.0]
    """
    return rows_cumsum(values, segment_rows(first_at, values.shape[0]))


#: Padding (elements) below which :func:`segment_rows` puts every segment in one group.
SMALL_PADDING = 1 << 16


class SegmentRows(NamedTuple):
    """Segments of ``N`` values laid out as rows of zero-padded tensors (:func:`segment_rows`).

    Attributes:
        groups: one ``(at, width)`` per group of rows: ``at`` the ``(rows * width,)`` int64
            position of each row's elements among the values, ``N`` (a slot past the end
            holding 0.0) for the padding.
        back: ``(N,)`` int64 position of each value in the groups' rows, one after another.
    """

    groups: list[tuple[Tensor, int]]
    back: Tensor


def segment_rows(first_at: Tensor, n: int, segment: Tensor | None = None) -> SegmentRows:
    """The rows of :func:`rows_cumsum`: each segment of ``N`` values as a row, by groups.

    Segments are grouped by length into powers of two (``width < 2 * length``), so the
    padding at most doubles the work and there are at most 64 groups, never a loop over
    segments; when the padding is small (a small call), one group as wide as the longest.

    Args:
        first_at: ``(S,)`` int64 start of each segment, ascending, the first 0.
        n: ``N``, the number of values.
        segment: ``(N,)`` int64 segment of each value, when the caller has it.

    Returns:
        The :class:`SegmentRows`.
    """
    device = first_at.device
    if n == 0:
        return SegmentRows([], torch.zeros(0, dtype=torch.int64, device=device))
    if segment is None:
        starts = torch.zeros(n, dtype=torch.bool, device=device)
        segment = run_index(starts.scatter_(0, first_at, True))
    length = torch.diff(first_at, append=first_at.new_tensor([n]))
    widest = int(length.max())
    if first_at.shape[0] * widest <= 2 * n + SMALL_PADDING:
        groups = [(_row_positions(first_at, length, widest, n), widest)]
        base = torch.arange(0, first_at.shape[0] * widest, widest, device=device)
    else:
        # Group k holds the segments of length in (2**(k-1), 2**k]: frexp's exponent of
        # length - 1.
        group = torch.frexp((length - 1).to(torch.float64)).exponent
        groups, base, offset = [], torch.empty_like(first_at), 0
        for k in torch.unique(group).tolist():
            members = where_true(group == k)
            size = members.shape[0] << k
            groups.append((_row_positions(take(first_at, members), take(length, members),
                                          1 << k, n), 1 << k))
            base.index_copy_(0, members, torch.arange(offset, offset + size, 1 << k,
                                                      device=device))
            offset += size
    back = take(base.sub_(first_at), segment).add_(torch.arange(n, device=device))
    return SegmentRows(groups, back)


def _row_positions(start: Tensor, size: Tensor, width: int, n: int) -> Tensor:
    offset = torch.arange(width, device=start.device)
    return (start[:, None] + offset).masked_fill_(offset >= size[:, None], n).reshape(-1)


def rows_cumsum(values: Tensor, rows: SegmentRows) -> Tensor:
    """The cumulative sums of each row of :func:`segment_rows` ``(first_at, N)``, from 0.

    Args:
        values: ``(N,)`` float64.
        rows: the segments' rows.

    Returns:
        ``(N,)`` float64 sums, each segment's bit for bit as if alone.
    """
    if not rows.groups:
        return torch.empty_like(values)
    # One slot past the end: the padding of every row reads its 0.0.
    padded = torch.cat([values, values.new_zeros(1)])
    sums = [torch.cumsum(take(padded, at).reshape(-1, width), 1).reshape(-1)
            for at, width in rows.groups]
    return take(sums[0] if len(sums) == 1 else torch.cat(sums), rows.back)


def linear_regions(knots: Knots, job: RegionJob) -> CurveCrossings:
    """The linear curve's solver: the crossings of the regions of one chunk, in region order.

    :class:`~evdown_torch.transforms.functional.estimation.driver.RegionJob` says what ``job``
    holds; ``front_at_rest`` changes nothing for polylines.
    """
    sensor_size, factor, fraction = job.sensor_size, job.factor, job.fraction
    emitted, resume = job.emitted, job.resume
    device = knots.t.device

    # Slope of every segment, stored at its first knot (0 after a pixel's last knot).
    k = knots.t.shape[0]
    first_at = where_true(knots.first)
    last_at = last_of_runs(first_at, k)
    rise = torch.empty(k, dtype=torch.int64, device=device)
    torch.sub(knots.level[1:], knots.level[:-1], out=rise[:-1])
    rise.scatter_(0, last_at, 0)
    run = torch.ones(k, dtype=torch.float64, device=device)
    run[:-1] = knots.t[1:] - knots.t[:-1]
    run.scatter_(0, last_at, 1.0)
    slope = rise.to(torch.float64).div_(run)
    del rise, run, last_at
    # Fixed point for the slope sums: high parts add exactly in int64, low parts are tiny.
    # One scale per region (a power of two from its own steepest slope), so that a region's
    # sums do not depend on the regions processed with it (a batch, a chunk of regions).
    nb = knots.bp_t.shape[0]
    bp = knots.breakpoint
    bp_first = knots.bp_first
    bp_first_at = where_true(bp_first)
    region = run_index(bp_first)
    knot_region = take(region, bp)
    steepest = torch.zeros(bp_first_at.shape[0], dtype=torch.float64, device=device)
    steepest.scatter_reduce_(0, knot_region, slope.abs(), "amax")
    exponent = torch.frexp(steepest * (factor[0] * factor[1])).exponent
    scale = torch.ldexp(torch.ones_like(steepest), 60 - exponent)
    scale.masked_fill_(steepest == 0, 1.0)
    knot_scale = take(scale, knot_region)
    del steepest, exponent, knot_region
    high_f = torch.round(slope * knot_scale)
    low = slope.sub_(high_f / knot_scale)
    high = high_f.to(torch.int64)
    del high_f, slope, knot_scale

    # Per breakpoint: slope-sum change (fixed point + rest), knot count.
    high_bp = torch.zeros(nb, dtype=torch.int64, device=device).index_add_(
        0, bp, differences(high, first_at)
    )
    low_bp = torch.zeros(nb, dtype=torch.float64, device=device).index_add_(
        0, bp, differences(low, first_at)
    )
    count = torch.bincount(bp, minlength=nb)
    del high, low, first_at, bp
    whole = breakpoint_levels(knots, bp_first_at, region)  # exact integer part of n_r * M_r
    # Each region's high parts add up to exactly 0 (every pixel's slope returns to 0 at its
    # last knot), so their plain cumulative sum restarts exactly at each region.
    slope_sum = torch.cumsum(high_bp, 0).to(torch.float64).div_(take(scale, region))
    rows = segment_rows(bp_first_at, nb, region)  # for both float sums
    slope_sum += rows_cumsum(low_bp, rows)
    del high_bp, low_bp
    # No pixel strictly inside a segment (all active pixels have a knot): remainder exactly 0.
    idle = count == take(take(count, bp_first_at), region)
    del count

    # Remainder (pixels' progress inside their segments) by a sweep, reset where it is 0.
    gap = torch.zeros(nb, dtype=torch.float64, device=device)
    gap[:-1] = knots.bp_t[1:] - knots.bp_t[:-1]
    gap.scatter_(0, last_of_runs(bp_first_at, nb), 0.0)
    step = torch.empty(nb, dtype=torch.float64, device=device)
    step[0] = 0.0
    torch.mul(slope_sum[:-1], gap[:-1], out=step[1:])
    step[1:] -= (whole[1:] - whole[:-1]).to(torch.float64)
    step.scatter_(0, bp_first_at, 0.0)
    del gap, slope_sum
    total = rows_cumsum(step, rows)
    part = total - take(take(total, where_true(idle)), run_index(idle))
    del step, total, idle

    # Reference rule on the breakpoints (each piece between breakpoints is monotone).
    pixels = region_pixels(knots, sensor_size, factor, region)
    floor_u, on_level = level_index(whole, part, pixels, fraction)
    floor_u, on_level, q_start = resume_moves(knots, None, floor_u, on_level, resume, region)
    cross = move_crossings(floor_u, on_level, bp_first, emitted=emitted, q_start=q_start)

    # Crossing times: linear interpolation on the piece that ends at the crossing's step.
    end = cross.move
    jump = take(bp_first, end)
    begin = end - (~jump).to(torch.int64)
    piece_pixels = pixels if isinstance(pixels, int) else take(pixels, end)
    target = level_value(cross.level, piece_pixels, fraction)
    whole_begin, part_begin = take(whole, begin), take(part, begin)
    rise_whole = (take(whole, end) - whole_begin).to(torch.float64)
    ratio = ((target - whole_begin.to(torch.float64)) - part_begin) / (
        rise_whole + (take(part, end) - part_begin)
    )
    at_end = jump | (take(on_level, end) & (cross.level == take(floor_u, end)))
    ratio = torch.where(at_end, 1.0, torch.nan_to_num(ratio).clamp(0.0, 1.0))
    t = piece_time(take(knots.bp_t, begin), take(knots.bp_t, end), ratio)
    return CurveCrossings(take(knots.regions, take(region, end)), t, cross.on, end)
