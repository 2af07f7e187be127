"""Linear log-luminance estimation kernel: exact crossings of the regions' mean polylines."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evdown_torch.checks import output_size
from evdown_torch.events import Events
from evdown_torch.transforms.functional._common import sort_by_time
from evdown_torch.transforms.functional._knots import (
    emit,
    level_changes,
    level_index,
    level_value,
    piece_time,
    pixel_knots,
    run_index,
    segmented_cumsum,
)
from evdown_torch.transforms.functional._reference import (
    crossings,
    reference_index,
    region_pixel_count,
)
from evdown_torch.transforms.functional.event_count import threshold_fraction


def _split(values: Tensor, scale: float) -> tuple[Tensor, Tensor]:
    """``values = high / scale + low`` with ``high`` int64 and ``|low| <= 0.5 / scale`` exact."""
    high = torch.round(values * scale)
    return high.to(torch.int64), values - high / scale


def linear_estimation(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    threshold: float,
) -> Events:
    """Downscale by linear log-luminance estimation (SEMANTICS.md method 4).

    Each pixel's log-luminance is the polyline through its knots (see
    :mod:`~evdown_torch.transforms.functional._knots`); each region's mean ``M_r`` (sum of its
    pixels' polylines over ``n_r``) is watched by the DVS reference rule at contrast
    ``threshold`` over ``[t_start, t_end]``, from level 0 just before ``t_start``. Events get
    the exact crossing times, rounded half up to integers when ``t`` is int64.

    The kernel sweeps each region's breakpoints once. ``n_r * M_r`` at a breakpoint is an
    exact integer (the levels of the pixels' latest knots) plus the progress of the pixels
    strictly inside a segment; that progress is the running integral of the region's slope,
    whose sum is kept in fixed point so that it does not drift, and it is exactly 0 wherever no
    pixel is inside a segment. All time arithmetic is relative to breakpoints, so shifting the
    clock shifts the output exactly.

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        threshold: contrast threshold ``theta`` on the region's mean level, > 0, used as the
            nearest fraction with denominator at most 10**6.

    Returns:
        Output events sorted by ``t``, ``t`` of the input's dtype.

    Example:
        >>> ev = Events.from_columns([0, 1], [0, 0], [0, 10], [1, 1])
        >>> out = linear_estimation(ev, sensor_size=(2, 1, 2), factor=(2, 1), threshold=0.25)
        >>> out.t.tolist(), out.p.tolist()
        ([0, 0, 5, 10], [True, True, True, True])
    """
    events = sort_by_time(events)
    device = events.device
    if events.num_events == 0:
        return Events.empty(events.t.dtype, device)
    fraction = threshold_fraction(threshold)
    out_w = output_size(sensor_size, factor)[0]
    knots = pixel_knots(events, factor=factor, out_width=out_w)

    # Slope of every segment, stored at its first knot (0 after a pixel's last knot).
    k = knots.t.shape[0]
    rise = torch.zeros(k, dtype=torch.int64, device=device)
    rise[:-1] = knots.level[1:] - knots.level[:-1]
    rise[knots.last] = 0
    run = torch.ones(k, dtype=torch.float64, device=device)
    run[:-1] = (knots.t[1:] - knots.t[:-1]).to(torch.float64)
    run[knots.last] = 1.0
    slope = rise.to(torch.float64) / run
    del rise, run
    # Fixed point for the slope sums: high parts add exactly in int64, low parts are tiny.
    bound = float(slope.abs().max()) * factor[0] * factor[1]
    scale = 2.0 ** (60 - math.frexp(bound)[1]) if bound > 0 else 1.0
    high, low = _split(slope, scale)
    del slope

    # Per knot, the changes it brings to its breakpoint: level (exact), slope sum, count.
    d_level = level_changes(knots)
    d_high, d_low = high.clone(), low.clone()
    d_high[1:] -= high[:-1]
    d_low[1:] -= low[:-1]
    d_high[knots.first] = high[knots.first]
    d_low[knots.first] = low[knots.first]
    del high, low
    nb = knots.bp_t.shape[0]
    ints = torch.stack((d_level, d_high, torch.ones_like(d_level)), 1)
    per_bp = torch.zeros(nb, 3, dtype=torch.int64, device=device).index_add_(
        0, knots.breakpoint, ints
    )
    bp_low = torch.zeros(nb, dtype=torch.float64, device=device).index_add_(
        0, knots.breakpoint, d_low
    )
    del ints, d_level, d_high, d_low
    bp_first = knots.bp_first
    whole = segmented_cumsum(per_bp[:, 0], bp_first)  # exact integer part of n_r * M_r
    slope_sum = torch.cumsum(per_bp[:, 1], 0).to(torch.float64) / scale + segmented_cumsum(
        bp_low, bp_first
    )
    count = per_bp[:, 2]
    active = count[bp_first][run_index(bp_first)]
    idle = count == active  # no pixel strictly inside a segment: the remainder is exactly 0

    # Remainder (pixels' progress inside their segments) by a sweep, reset where it is 0.
    gap = torch.zeros(nb, dtype=torch.float64, device=device)
    gap[:-1] = (knots.bp_t[1:] - knots.bp_t[:-1]).to(torch.float64)
    gap[knots.bp_last] = 0.0
    step = torch.zeros(nb, dtype=torch.float64, device=device)
    step[1:] = (slope_sum * gap)[:-1] - (whole[1:] - whole[:-1]).to(torch.float64)
    step[bp_first] = 0.0
    total = torch.cumsum(step, 0)
    part = total - total[idle][run_index(idle)]
    del step, total, slope_sum

    # Reference rule on the breakpoints (each piece between breakpoints is monotone).
    pixels = region_pixel_count(knots.bp_region, sensor_size, factor)
    floor_u, on_level = level_index(whole, part, pixels, fraction)
    zero = torch.zeros_like(floor_u)
    q = reference_index(floor_u, on_level, bp_first, zero)
    q_before = torch.empty_like(q)
    q_before[1:] = q[:-1]
    q_before[bp_first] = 0
    cross = crossings(q_before, q)

    # Crossing times: linear interpolation on the piece that ends at the crossing's step.
    end = cross.step
    jump = bp_first[end]
    begin = torch.where(jump, end, end - 1)
    target = level_value(cross.level, pixels[end], fraction)
    rise_whole = (whole[end] - whole[begin]).to(torch.float64)
    ratio = ((target - whole[begin].to(torch.float64)) - part[begin]) / (
        rise_whole + (part[end] - part[begin])
    )
    at_end = jump | (on_level[end] & (cross.level == floor_u[end]))
    ratio = torch.where(at_end, 1.0, torch.nan_to_num(ratio).clamp(0.0, 1.0))
    t = piece_time(knots.bp_t[begin], knots.bp_t[end], ratio)
    return emit(knots.bp_region[end], t, cross.on, out_w)
