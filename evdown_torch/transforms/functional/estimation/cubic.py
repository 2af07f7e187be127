"""Cubic log-luminance estimation kernel: PCHIP pixel curves, crossings solved per piece."""

from __future__ import annotations

import torch
from torch import Tensor

from evdown_torch._tensors import (
    CHUNK_EVENTS,
    correctly_rounded_sqrt,
    run_index,
    take,
    where_true,
)
from evdown_torch.transforms.functional.estimation.knots import Knots, piece_time, region_pixels
from evdown_torch.transforms.functional.estimation.solver import (
    CurveCrossings,
    RegionJob,
    breakpoint_levels,
    resume_moves,
)
from evdown_torch.transforms.functional.reference import level_index, level_value, move_crossings

__all__ = ["cubic_regions", "pchip_slopes"]

#: Pixel-segment evaluations per chunk: bounds the kernel's memory and keeps its temporary
#: tensors small enough to be recycled by the allocator instead of faulted in afresh.
CHUNK = 1 << 16

#: Extrema of a piece closer than this (in the piece's normalised time) to its ends are
#: ignored: the curve cannot move by a float-visible amount there.
EDGE = 1e-9

#: Relative size of a derivative's discriminant below which its roots count as one double root.
DOUBLE_ROOT = 1e-12

#: Most iterations of the safeguarded Newton solver (each at least halves the bracket).
MAX_ITERATIONS = 100


def _shift(values: Tensor, by: int, fill: float | int | bool) -> Tensor:
    """``values`` moved ``by`` places to the right (left when negative), padded with ``fill``."""
    out = torch.empty_like(values)
    if by > 0:
        out[by:] = values[:-by]
        out[:by] = fill
    else:
        out[:by] = values[-by:]
        out[by:] = fill
    return out


def _edge_slope(h0: Tensor, h1: Tensor, m0: Tensor, m1: Tensor) -> Tensor:
    """SciPy's one-sided three-point end slope of ``PchipInterpolator``, shape-preserving."""
    d = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
    flip = torch.sign(d) != torch.sign(m0)
    steep = (torch.sign(m0) != torch.sign(m1)) & (d.abs() > 3 * m0.abs())
    return torch.where(flip, 0.0, torch.where(steep, 3 * m0, d))


def pchip_slopes(knots: Knots, *, front_at_rest: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Derivative of every pixel's PCHIP curve at each knot, by SciPy's rules.

    Args:
        knots: the :class:`~evdown_torch.transforms.functional.estimation.knots.Knots`.
        front_at_rest: the slope at each pixel's first knot is 0 instead of SciPy's end
            slope (a bounded delay, docs/semantics.md "Bounded delay": SciPy's end slope
            depends on the width of the pixel's second segment, which input arbitrarily
            later decides). In a streaming window a pixel's first knot is either its first
            in the stream or one kept before the window's cut, whose slope shapes only a
            piece that the window does not solve.

    Returns:
        ``(slope, width, rise)``, all ``(K,)`` float64: the derivative at each knot (level per
        time unit), and the duration and level change of the segment that starts at each knot
        (width 1, rise 0 after a pixel's last knot).
    """
    first, last = knots.first, knots.last
    k = knots.t.shape[0]
    last_at = where_true(last)
    # Segments between consecutive knots (K + 1 entries, so that shifted views need no copy).
    width_ext = torch.ones(k + 1, dtype=torch.float64, device=knots.t.device)
    torch.sub(knots.t[1:], knots.t[:-1], out=width_ext[1:-1])
    rise_ext = torch.zeros_like(width_ext)
    torch.sub(knots.level[1:], knots.level[:-1], out=rise_ext[1:-1])
    width_ext.scatter_(0, last_at + 1, 1.0)  # no segment after a pixel's last knot
    rise_ext.scatter_(0, last_at + 1, 0.0)
    m_ext = rise_ext / width_ext
    width, rise, m_next = width_ext[1:], rise_ext[1:], m_ext[1:]
    w_prev, m_prev = width_ext[:-1], m_ext[:-1]
    # Interior knots: Fritsch-Carlson weighted harmonic mean, 0 at extrema and flat segments
    # (slopes are at least 1 / 2**63 in size, so their product cannot underflow to 0).
    flat = (m_next * m_prev) <= 0
    w1 = torch.add(w_prev, width, alpha=2.0)
    w2 = torch.add(width, w_prev, alpha=2.0)
    slope = torch.add(w1, w2).div_(torch.div(w1, m_prev).add_(w2.div_(m_next)))
    slope.masked_fill_(flat, 0.0)
    del flat, w1, w2
    # End knots: two knots give a line, three or more SciPy's one-sided estimate.
    first_at = where_true(first)
    # The knots after a first and before a last (clamped: a pixel with one knot is set below).
    after = torch.clamp(first_at + 1, max=first.shape[0] - 1)
    before = torch.clamp(last_at - 1, min=0)
    two = take(last, after)  # the pixel has exactly two knots
    if front_at_rest:
        front = torch.zeros(first_at.shape, dtype=torch.float64, device=first_at.device)
    else:
        front = torch.where(
            two,
            take(m_next, first_at),
            _edge_slope(take(width, first_at), take(width, after), take(m_next, first_at),
                        take(m_next, after)),
        )
    back = torch.where(
        two,
        take(m_prev, last_at),
        _edge_slope(
            take(w_prev, last_at), take(w_prev, before), take(m_prev, last_at), take(m_prev, before)
        ),
    )
    slope.scatter_(0, first_at, front)
    slope.scatter_(0, last_at, back)
    single = where_true(first & last)  # one knot: a constant (t_start == t_end)
    slope.scatter_(0, single, 0.0)
    return slope, width, rise


def _mid_segment_sums(
    knots: Knots, slope: Tensor, width: Tensor, rise: Tensor
) -> tuple[Tensor, Tensor]:
    """Value and derivative of the pixels strictly inside a segment, summed per breakpoint.

    The value is measured from the segment's start (its rise above it).

    Every (segment, breakpoint strictly inside it) pair is evaluated in the segment's
    normalised time ``s = (b - t_k) / width`` in chunks of :data:`CHUNK` pairs, and added into
    its breakpoint in pair order (segments ascending), so each sum is the same float however
    the pairs are chunked. Segments on which the curve is constant are skipped.
    """
    device = slope.device
    nb = knots.bp_t.shape[0]
    value_sum = torch.zeros(nb, dtype=torch.float64, device=device)
    slope_sum = torch.zeros(nb, dtype=torch.float64, device=device)
    bp = knots.breakpoint
    inside = torch.zeros_like(bp)
    torch.sub(bp[1:], bp[:-1], out=inside[:-1]).sub_(1)
    inside.scatter_(0, where_true(knots.last), 0)
    c1 = width * slope
    c2_end = _shift(slope, -1, 0.0).mul_(width)
    moving = c1 != 0
    moving |= c2_end != 0
    moving |= rise != 0
    moving &= inside > 0
    segments = where_true(moving)
    del moving
    if segments.shape[0] == 0:
        return value_sum, slope_sum
    counts = take(inside, segments)
    del inside
    # Per segment: start, first breakpoint inside, and the Hermite coefficients in s.
    start_t = take(knots.t, segments)
    if knots.t.is_floating_point():
        bp_time = knots.bp_t
    else:  # exact: integer offsets from t_start below 2**53
        bp_time = (knots.bp_t - knots.t[0]).to(torch.float64)
        start_t = (start_t - knots.t[0]).to(torch.float64)
    c1 = take(c1, segments)
    c2_end = take(c2_end, segments)
    r = take(rise, segments)
    # In place, as 3 r - 2 c1 - c2_end and c1 + c2_end - 2 r (the doubling is exact).
    c2 = torch.mul(r, 3).sub_(c1, alpha=2.0).sub_(c2_end)
    c3 = torch.add(c1, c2_end).sub_(r, alpha=2.0)
    inv_w = take(width, segments).reciprocal_()
    del c2_end, r
    cum = torch.cumsum(counts, 0)
    total = int(cum[-1])
    begin = cum - counts  # first pair of each segment
    # The breakpoint of each pair advances by 1 inside a segment and by jump[j - 1] from the last
    # pair of segment j - 1 to the first of segment j.
    first = take(bp, segments) + 1
    jump = first[1:] - first[:-1]
    jump -= counts[:-1]
    jump += 1
    del segments
    # The segments [low, high) of each chunk's pairs, and its first pair's breakpoint.
    chunk_start = torch.arange(0, total, CHUNK, device=device)
    low = torch.searchsorted(cum, chunk_start, right=True)
    first_target = take(first, low) + chunk_start - take(begin, low)
    last = torch.clamp(chunk_start + (CHUNK - 1), max=total - 1)
    high = torch.searchsorted(cum, last, right=True) + 1
    lows, highs, first_targets = low.tolist(), high.tolist(), first_target.tolist()
    del counts, cum, first, chunk_start, low, high, first_target, last
    # Buffers reused by every chunk: fresh temporaries would be faulted in each time.
    size = min(CHUNK, total)
    ints = torch.empty(4, size, dtype=torch.int64, device=device)
    floats = torch.empty(7, size, dtype=torch.float64, device=device)
    for i, start in enumerate(range(0, total, CHUNK)):
        m = min(start + CHUNK, total) - start
        lo, hi = lows[i], highs[i]
        starts, stride, seg, target = ints[0, : hi - lo - 1], ints[1, :m], ints[2, :m], ints[3, :m]
        s, a1, a2, a3, w, u, v = (row[:m] for row in floats)
        # Pairs [start, start + m) of segments [lo, hi): the segment and breakpoint of each
        # pair, as cumulative sums of their strides from pair to pair.
        torch.sub(begin[lo + 1 : hi], start, out=starts)
        stride.zero_()
        stride.index_fill_(0, starts, 1)
        stride[0] = lo
        torch.cumsum(stride, 0, out=seg)
        stride.fill_(1)
        stride.index_copy_(0, starts, jump[lo : hi - 1])
        stride[0] = first_targets[i]
        torch.cumsum(stride, 0, out=target)
        torch.index_select(bp_time, 0, target, out=s)
        s -= torch.index_select(start_t, 0, seg, out=a1)
        s *= torch.index_select(inv_w, 0, seg, out=w)
        torch.index_select(c1, 0, seg, out=a1)
        torch.index_select(c2, 0, seg, out=a2)
        torch.index_select(c3, 0, seg, out=a3)
        torch.addcmul(a2, s, a3, out=u)  # c2 + s c3
        torch.addcmul(a1, s, u, out=v)
        v *= s  # s (c1 + s (c2 + s c3))
        # scatter_add_ adds in pair order as index_add_ does (on the CPU), at half its cost.
        value_sum.scatter_add_(0, target, v)
        a3 *= s
        a3.add_(u, alpha=2.0)  # 2 c2 + 3 c3 s
        torch.addcmul(a1, s, a3, out=v)
        v *= w  # derivative per time unit
        slope_sum.scatter_add_(0, target, v)
    return value_sum, slope_sum


def _derivative_roots(c1: Tensor, c2: Tensor, c3: Tensor) -> tuple[Tensor, Tensor]:
    """Sign changes of ``c1 + 2 c2 s + 3 c3 s^2`` inside ``(EDGE, 1 - EDGE)``, ascending.

    The roots are ``q / (3 c3)`` and ``c1 / q`` with ``q = -(c2 + sign(c2) sqrt(c2^2 -
    3 c1 c3))``, free of cancellation; when ``c3 = 0`` the first is infinite and the second is
    the linear root ``-c1 / (2 c2)``.

    Returns:
        ``(low, high)``; missing roots are NaN.
    """
    square = c2 * c2
    disc = torch.addcmul(square, c1, c3, value=-3.0)
    # NaN where disc < 0; correctly rounded, as the compiled solver's (torch's CPU sqrt is not)
    q = correctly_rounded_sqrt(disc).copysign_(c2).add_(c2).neg_()
    # A double root is no sign change; within float noise of one, the curve cannot move by a
    # visible amount between the two roots (PCHIP pieces such as 1 - (1 - s)^3 have one).
    noise = square.addcmul_(c1, c3, value=3.0).abs_().mul_(DOUBLE_ROOT)
    q.masked_fill_(disc <= noise, torch.nan)
    del square, disc, noise
    r1 = torch.mul(c3, 3)
    torch.div(q, r1, out=r1)
    r2 = torch.div(c1, q, out=q)
    r1.masked_fill_(~((r1 > EDGE) & (r1 < 1 - EDGE)), torch.nan)
    r2.masked_fill_(~((r2 > EDGE) & (r2 < 1 - EDGE)), torch.nan)
    low, high = torch.fmin(r1, r2), torch.fmax(r1, r2)
    high.masked_fill_(~(high > low), torch.nan)
    return low, high


def _solve(
    c1: Tensor, c2: Tensor, c3: Tensor, goal: Tensor, low: Tensor, high: Tensor, rising: Tensor
) -> Tensor:
    """Root of ``s (c1 + s (c2 + s c3)) = goal`` in ``[low, high]``, where the cubic is monotone.

    The cubic is rising or falling there; Newton's method, safeguarded by bisection.

    Each root leaves the iteration once its last update moved it by at most 1e-15, so the cost
    follows the number of roots (most converge in a few iterations), not the slowest one.
    """
    sign = torch.where(rising, 1.0, -1.0)

    def poly(s: Tensor, c1: Tensor, c2: Tensor, c3: Tensor) -> Tensor:
        return s * (c1 + s * (c2 + s * c3))

    at_low, at_high = poly(low, c1, c2, c3), poly(high, c1, c2, c3)
    x = low + (goal - at_low) / (at_high - at_low) * (high - low)
    x = torch.where(torch.isfinite(x), x.clamp(min=0.0, max=1.0), 0.5 * (low + high))
    x = torch.minimum(torch.maximum(x, low), high)
    root = x.clone()
    active = torch.arange(x.shape[0], device=x.device)
    for _ in range(MAX_ITERATIONS):
        if active.shape[0] == 0:
            break
        g = sign * (poly(x, c1, c2, c3) - goal)
        low = torch.where(g < 0, x, low)
        high = torch.where(g > 0, x, high)
        newton = x - g / (sign * (c1 + x * (2 * c2 + 3 * c3 * x)))
        inside = (newton > low) & (newton < high)
        update = torch.where(g == 0, x, torch.where(inside, newton, 0.5 * (low + high)))
        moving = (update - x).abs() > 1e-15
        x = update
        root.scatter_(0, active, x)
        if not bool(moving.all()):  # drop the converged roots
            keep = where_true(moving)
            active, x, low, high, goal, sign, c1, c2, c3 = (
                take(v, keep) for v in (active, x, low, high, goal, sign, c1, c2, c3)
            )
    return root


def _monotone_moves(
    low: Tensor, high: Tensor, prev: Tensor, whole: Tensor, part: Tensor,
    c1: Tensor, c2: Tensor, c3: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The monotone moves: each piece's interior extrema (if any), then its end.

    Returns:
        ``(move_bp, move_s, move_whole, move_part)``: for each move in order, the breakpoint
        its piece ends at, its end in the piece's normalised time (1 at the breakpoint), and
        ``n_r * M_r`` there as an exact integer part plus a float rest.
    """
    nb = low.shape[0]
    has_low, has_high = ~torch.isnan(low), ~torch.isnan(high)
    if not bool(has_low.any()):
        return torch.arange(nb, device=low.device), torch.ones_like(low), whole, part
    roots = has_low.to(torch.int64) + has_high.to(torch.int64)
    end_pos = torch.cumsum(roots, 0)
    end_pos += torch.arange(nb, device=low.device)  # a piece's end comes after its roots
    total = int(end_pos[-1]) + 1
    move_bp = torch.empty(total, dtype=torch.int64, device=low.device)
    move_bp.scatter_(0, end_pos, torch.arange(nb, device=low.device))
    move_s = torch.ones(total, dtype=torch.float64, device=low.device)
    move_whole = torch.empty(total, dtype=torch.int64, device=low.device)
    move_whole.scatter_(0, end_pos, whole)
    move_part = torch.empty(total, dtype=torch.float64, device=low.device)
    move_part.scatter_(0, end_pos, part)
    low_at, high_at = where_true(has_low), where_true(has_high)
    for at, s, pos in (
        (low_at, take(low, low_at), take(end_pos, low_at) - take(roots, low_at)),
        (high_at, take(high, high_at), take(end_pos, high_at) - 1),
    ):
        begin = take(prev, at)
        value = torch.addcmul(take(c2, at), s, take(c3, at))
        value = torch.addcmul(take(c1, at), s, value, out=value)
        value *= s
        value += take(part, begin)
        move_bp.scatter_(0, pos, at)
        move_s.scatter_(0, pos, s)
        move_whole.scatter_(0, pos, take(whole, begin))
        move_part.scatter_(0, pos, value)
    return move_bp, move_s, move_whole, move_part


def cubic_regions(knots: Knots, job: RegionJob) -> CurveCrossings:
    """The cubic curve's solver: the crossings of the regions of one chunk, in region order.

    :class:`~evdown_torch.transforms.functional.estimation.driver.RegionJob` says what ``job``
    holds. With ``job.front_at_rest`` each pixel's slope at its first knot is 0
    (``pchip_slopes``).
    """
    sensor_size, factor, fraction = job.sensor_size, job.factor, job.fraction
    emitted, resume, front_at_rest = job.emitted, job.resume, job.front_at_rest
    device = knots.t.device
    slope, width, rise = pchip_slopes(knots, front_at_rest=front_at_rest)

    # n_r * M_r and its derivative at every breakpoint: exact integer part + the rest.
    nb = knots.bp_t.shape[0]
    bp_first = knots.bp_first
    bp_first_at = where_true(bp_first)
    whole = breakpoint_levels(knots, bp_first_at, run_index(bp_first))
    part, derivative = _mid_segment_sums(knots, slope, width, rise)
    derivative.scatter_add_(0, knots.breakpoint, slope)
    del slope, width, rise

    # The piece ending at each breakpoint (none before a region's first), normalised time.
    prev = torch.arange(-1, nb - 1, device=device)
    prev[bp_first_at] = bp_first_at  # a region's first move is a jump, not a piece
    gap = (knots.bp_t - take(knots.bp_t, prev)).to(torch.float64)
    change = (whole - take(whole, prev)).to(torch.float64) + (part - take(part, prev))
    m0, m1 = take(derivative, prev).mul_(gap), derivative.mul_(gap)
    del gap, derivative
    c1 = m0
    c2 = torch.mul(change, 3).sub_(m0, alpha=2.0).sub_(m1)  # 3 change - 2 m0 - m1
    c3 = torch.add(m0, m1).sub_(change, alpha=2.0)  # m0 + m1 - 2 change
    del m1, change
    for c in (c1, c2, c3):
        c.scatter_(0, bp_first_at, 0.0)
    low, high = _derivative_roots(c1, c2, c3)

    # Monotone moves: up to two interior extrema, then the breakpoint (a jump at t_start).
    move_bp, move_s, move_whole, move_part = _monotone_moves(
        low, high, prev, whole, part, c1, c2, c3
    )
    del low, high
    is_end = move_s == 1.0
    pixels = region_pixels(knots, sensor_size, factor)
    move_pixels = pixels if isinstance(pixels, int) else take(pixels, move_bp)
    floor_u, on_level = level_index(move_whole, move_part, move_pixels, fraction)
    move_first = take(bp_first, move_bp) & is_end
    floor_u, on_level, q_start = resume_moves(knots, move_bp, floor_u, on_level, resume)
    cross = move_crossings(floor_u, on_level, move_first, emitted=emitted, q_start=q_start)
    del move_first, is_end, move_whole, move_part

    # Solve each crossing on its monotone move (the move before it ends where it starts), in
    # chunks of crossings so that the solver's temporaries stay small however many there are.
    def crossing_times(e: Tensor, level: Tensor, on: Tensor) -> Tensor:
        i = take(move_bp, e)
        jump = take(bp_first, i)
        s_high = take(move_s, e)
        before = torch.clamp(e - 1, min=0)
        s_low = torch.where(take(move_bp, before) == i, take(move_s, before), 0.0)
        s_low = torch.where(jump, s_high, s_low)
        begin = take(prev, i)
        piece_pixels = pixels if isinstance(pixels, int) else take(pixels, i)
        goal = level_value(level, piece_pixels, fraction)
        goal -= take(whole, begin).to(torch.float64)
        goal -= take(part, begin)
        s = _solve(take(c1, i), take(c2, i), take(c3, i), goal, s_low, s_high, on)
        at_end = jump | (take(on_level, e) & (level == take(floor_u, e)))
        s = torch.where(at_end, s_high, s)
        return piece_time(take(knots.bp_t, begin), take(knots.bp_t, i), s)

    k = cross.move.shape[0]
    t = torch.cat([
        crossing_times(cross.move[lo:lo + CHUNK_EVENTS], cross.level[lo:lo + CHUNK_EVENTS],
                       cross.on[lo:lo + CHUNK_EVENTS])
        for lo in range(0, max(k, 1), CHUNK_EVENTS)
    ])
    bp = take(move_bp, cross.move)
    return CurveCrossings(knots.bp_region(bp), t, cross.on, bp)
