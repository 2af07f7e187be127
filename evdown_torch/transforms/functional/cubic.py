"""Cubic log-luminance estimation kernel: PCHIP pixel curves, crossings solved per piece."""

from __future__ import annotations

import torch
from torch import Tensor

from evdown_torch.checks import output_size
from evdown_torch.events import Events
from evdown_torch.transforms.functional._common import sort_by_time
from evdown_torch.transforms.functional._knots import (
    Knots,
    emit,
    level_changes,
    level_index,
    level_value,
    piece_time,
    pixel_knots,
    repeat_index,
    segmented_cumsum,
)
from evdown_torch.transforms.functional._reference import (
    crossings,
    reference_index,
    region_pixel_count,
)
from evdown_torch.transforms.functional.event_count import threshold_fraction

#: Pixel-segment evaluations per memory chunk (bounds the kernel's peak memory).
CHUNK = 1 << 22

#: Extrema of a piece closer than this (in the piece's normalised time) to its ends are
#: ignored: the curve cannot move by a float-visible amount there.
EDGE = 1e-9

#: Most iterations of the safeguarded Newton solver (each at least halves the bracket).
MAX_ITERATIONS = 100


def _shift(values: Tensor, by: int, fill: float | int) -> Tensor:
    """``values`` moved ``by`` places to the right (left when negative), padded with ``fill``."""
    out = torch.full_like(values, fill)
    if by > 0:
        out[by:] = values[:-by]
    else:
        out[:by] = values[-by:]
    return out


def _edge_slope(h0: Tensor, h1: Tensor, m0: Tensor, m1: Tensor) -> Tensor:
    """SciPy's one-sided three-point end slope of ``PchipInterpolator``, shape-preserving."""
    d = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
    flip = torch.sign(d) != torch.sign(m0)
    steep = (torch.sign(m0) != torch.sign(m1)) & (d.abs() > 3 * m0.abs())
    return torch.where(flip, 0.0, torch.where(steep, 3 * m0, d))


def pchip_slopes(knots: Knots) -> tuple[Tensor, Tensor, Tensor]:
    """Derivative of every pixel's PCHIP curve at each knot, by SciPy's rules.

    Args:
        knots: the :class:`~evdown_torch.transforms.functional._knots.Knots`.

    Returns:
        ``(slope, width, rise)``, all ``(K,)`` float64: the derivative at each knot (level per
        time unit), and the duration and level change of the segment that starts at each knot
        (width 1, rise 0 after a pixel's last knot).
    """
    first, last = knots.first, knots.last
    width = torch.ones(knots.t.shape[0], dtype=torch.float64, device=knots.t.device)
    width[:-1] = (knots.t[1:] - knots.t[:-1]).to(torch.float64)
    width[last] = 1.0
    rise = _shift(knots.level, -1, 0) - knots.level
    rise[last] = 0
    rise = rise.to(torch.float64)
    m_next = rise / width
    w_prev, m_prev = _shift(width, 1, 1.0), _shift(m_next, 1, 0.0)
    # Interior knots: Fritsch-Carlson weighted harmonic mean, 0 at extrema and flat segments.
    flat = (torch.sign(m_next) != torch.sign(m_prev)) | (m_next == 0) | (m_prev == 0)
    w1 = 2 * width + w_prev
    w2 = width + 2 * w_prev
    harmonic = (w1 + w2) / (w1 / m_prev + w2 / m_next)
    slope = torch.where(flat, 0.0, harmonic)
    # End knots: two knots give a line, three or more SciPy's one-sided estimate.
    front = _edge_slope(width, _shift(width, -1, 1.0), m_next, _shift(m_next, -1, 0.0))
    back = _edge_slope(w_prev, _shift(w_prev, 1, 1.0), m_prev, _shift(m_prev, 1, 0.0))
    two_after = _shift(last, -1, True)
    two_before = _shift(first, 1, True)
    slope = torch.where(first, torch.where(two_after, m_next, front), slope)
    slope = torch.where(last, torch.where(two_before, m_prev, back), slope)
    slope[first & last] = 0.0
    return slope, width, rise


def _mid_segment_sums(
    knots: Knots, slope: Tensor, width: Tensor, rise: Tensor
) -> tuple[Tensor, Tensor]:
    """Value above the segment start and derivative of the pixels strictly inside a segment,
    summed per breakpoint (chunked, so memory stays bounded)."""
    device = slope.device
    nb = knots.bp_t.shape[0]
    sums = torch.zeros(nb, 2, dtype=torch.float64, device=device)
    bp = knots.breakpoint
    inside = _shift(bp, -1, 0) - bp - 1
    inside[knots.last] = 0
    # Hermite coefficients of each segment in its normalised time s in [0, 1].
    c1 = width * slope
    c2_end = width * _shift(slope, -1, 0.0)
    c2 = 3 * rise - 2 * c1 - c2_end
    c3 = c1 + c2_end - 2 * rise
    del c2_end
    segments = torch.nonzero(inside).squeeze(1)
    counts = inside[segments]
    cum = torch.cumsum(counts, 0)
    total = int(cum[-1]) if cum.numel() else 0
    for start in range(0, total, CHUNK):
        stop = min(start + CHUNK, total)
        lo = int(torch.searchsorted(cum, start, right=True))
        hi = int(torch.searchsorted(cum, stop - 1, right=True)) + 1
        part = counts[lo:hi].clone()
        offset = cum[lo:hi] - counts[lo:hi]
        skip = start - int(offset[0])
        part[0] -= skip
        part[-1] -= int(cum[hi - 1]) - stop
        local = repeat_index(part)
        seg = segments[lo:hi][local]
        within = torch.arange(stop - start, device=device) - (
            torch.cumsum(part, 0) - part
        )[local]
        within[: int(part[0])] += skip
        target = bp[seg] + 1 + within
        s = (knots.bp_t[target] - knots.t[seg]).to(torch.float64) / width[seg]
        a1, a2, a3 = c1[seg], c2[seg], c3[seg]
        value = s * (a1 + s * (a2 + s * a3))
        derivative = (a1 + s * (2 * a2 + 3 * a3 * s)) / width[seg]
        sums.index_add_(0, target, torch.stack((value, derivative), 1))
    return sums[:, 0], sums[:, 1]


def _derivative_roots(c1: Tensor, c2: Tensor, c3: Tensor) -> tuple[Tensor, Tensor]:
    """Sign changes of ``c1 + 2 c2 s + 3 c3 s^2`` inside ``(EDGE, 1 - EDGE)``, ascending.

    Returns:
        ``(low, high)``; missing roots are NaN.
    """
    a, b, c = 3 * c3, 2 * c2, c1
    disc = b * b - 4 * a * c
    root = torch.sqrt(torch.clamp(disc, min=0.0))
    q = -0.5 * (b + torch.where(b < 0, -root, root))  # no cancellation
    quadratic = (a != 0) & (disc > 0)
    r1 = torch.where(quadratic, q / a, torch.where((a == 0) & (b != 0), -c / b, torch.nan))
    r2 = torch.where(quadratic & (q != 0), c / q, torch.nan)
    r1 = torch.where((r1 > EDGE) & (r1 < 1 - EDGE), r1, torch.nan)
    r2 = torch.where((r2 > EDGE) & (r2 < 1 - EDGE), r2, torch.nan)
    low, high = torch.fmin(r1, r2), torch.fmax(r1, r2)
    return low, torch.where(high > low, high, torch.nan)


def _solve(
    c1: Tensor, c2: Tensor, c3: Tensor, goal: Tensor, low: Tensor, high: Tensor, rising: Tensor
) -> Tensor:
    """Root of ``s (c1 + s (c2 + s c3)) = goal`` in ``[low, high]``, where the cubic is monotone
    (rising or falling), by Newton's method safeguarded by bisection."""
    sign = torch.where(rising, 1.0, -1.0)

    def poly(s: Tensor) -> Tensor:
        return s * (c1 + s * (c2 + s * c3))

    at_low, at_high = poly(low), poly(high)
    x = low + (goal - at_low) / (at_high - at_low) * (high - low)
    x = torch.where(torch.isfinite(x), x.clamp(min=0.0, max=1.0), 0.5 * (low + high))
    x = torch.minimum(torch.maximum(x, low), high)
    for _ in range(MAX_ITERATIONS):
        g = sign * (poly(x) - goal)
        low = torch.where(g < 0, x, low)
        high = torch.where(g > 0, x, high)
        newton = x - g / (sign * (c1 + x * (2 * c2 + 3 * c3 * x)))
        inside = (newton > low) & (newton < high)
        step = torch.where(g == 0, x, torch.where(inside, newton, 0.5 * (low + high)))
        moved = (step - x).abs()
        x = step
        if x.numel() == 0 or float(moved.max()) <= 1e-15:
            break
    return x


def cubic_estimation(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    threshold: float,
) -> Events:
    """Downscale by cubic log-luminance estimation (SEMANTICS.md method 5).

    Each pixel's log-luminance is the piecewise cubic Hermite interpolant of its knots (see
    :mod:`~evdown_torch.transforms.functional._knots`) with SciPy's ``PchipInterpolator``
    slopes; each region's mean ``M_r`` is watched by the DVS reference rule at contrast
    ``threshold`` over ``[t_start, t_end]``, from level 0 just before ``t_start``. Events get
    the crossing times, rounded half up to integers when ``t`` is int64.

    Between two breakpoints (consecutive knot times of a region) ``M_r`` is one cubic, known
    from its values and derivatives at both ends. Those are sums over the region's pixels: an
    exact integer part (the levels of pixels with a knot there) plus the pixels strictly inside
    a segment, evaluated in each segment's normalised time. Each piece is split at the roots of
    its derivative into monotone steps for the reference rule, and each crossing is solved on
    its monotone step, in the piece's normalised time, by safeguarded Newton iterations to
    about 1e-15 of the piece's length.

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
        >>> out = cubic_estimation(ev, sensor_size=(2, 1, 2), factor=(2, 1), threshold=0.25)
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
    slope, width, rise = pchip_slopes(knots)

    # n_r * M_r and its derivative at every breakpoint: exact integer part + the rest.
    nb = knots.bp_t.shape[0]
    bp_first = knots.bp_first
    per_bp = torch.zeros(nb, dtype=torch.int64, device=device).index_add_(
        0, knots.breakpoint, level_changes(knots)
    )
    whole = segmented_cumsum(per_bp, bp_first)
    part, derivative = _mid_segment_sums(knots, slope, width, rise)
    derivative.index_add_(0, knots.breakpoint, slope)
    del slope, width, rise, per_bp

    # The piece ending at each breakpoint (none before a region's first), normalised time.
    prev = torch.clamp(torch.arange(nb, device=device) - 1, min=0)
    gap = (knots.bp_t - knots.bp_t[prev]).to(torch.float64)
    change = (whole - whole[prev]).to(torch.float64) + (part - part[prev])
    m0, m1 = gap * derivative[prev], gap * derivative
    c1 = torch.where(bp_first, 0.0, m0)
    c2 = torch.where(bp_first, 0.0, 3 * change - 2 * m0 - m1)
    c3 = torch.where(bp_first, 0.0, m0 + m1 - 2 * change)
    del m0, m1, derivative, change
    low, high = _derivative_roots(c1, c2, c3)

    # Monotone steps: up to two interior extrema, then the breakpoint (a jump at t_start).
    ends = torch.stack((low, high, torch.ones_like(low)), 1)
    valid = ~torch.isnan(ends)
    step_bp = torch.arange(nb, device=device).unsqueeze(1).expand(nb, 3)[valid]
    step_s = ends[valid]
    del ends, valid, low, high
    start = prev[step_bp]
    is_end = step_s == 1.0
    inner = step_s * (c1[step_bp] + step_s * (c2[step_bp] + step_s * c3[step_bp]))
    step_whole = torch.where(is_end, whole[step_bp], whole[start])
    step_part = torch.where(is_end, part[step_bp], part[start] + inner)
    del inner
    pixels = region_pixel_count(knots.bp_region[step_bp], sensor_size, factor)
    floor_u, on_level = level_index(step_whole, step_part, pixels, fraction)
    step_first = bp_first[step_bp] & is_end
    q = reference_index(floor_u, on_level, step_first, torch.zeros_like(floor_u))
    q_before = _shift(q, 1, 0)
    q_before[step_first] = 0
    cross = crossings(q_before, q)

    # Solve each crossing on its monotone step.
    e = cross.step
    i = step_bp[e]
    jump = bp_first[i]
    s_high = step_s[e]
    s_low = torch.where(step_bp[e - 1] == i, step_s[e - 1], 0.0) if e.numel() else s_high
    s_low = torch.where(jump, s_high, s_low)
    begin = prev[i]
    goal = (level_value(cross.level, pixels[e], fraction) - whole[begin].to(torch.float64)) - part[
        begin
    ]
    s = _solve(c1[i], c2[i], c3[i], goal, s_low, s_high, cross.on)
    at_end = jump | (on_level[e] & (cross.level == floor_u[e]))
    s = torch.where(at_end, s_high, s)
    t = piece_time(knots.bp_t[begin], knots.bp_t[i], s)
    return emit(knots.bp_region[i], t, cross.on, out_w)
