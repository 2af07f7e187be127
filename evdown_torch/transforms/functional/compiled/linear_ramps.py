"""LinearEstimation's compiled bounded-delay session: ramps in two rings, swept in fixed point.

A bounded-delay session of the linear estimator with int64 timestamps takes this path on the
CPU (:mod:`.linear_stream`): two passes over each chunk, no window and no sort, where the
windowed driver (:mod:`..estimation.stream`) groups and sorts every chunk's knot events.

* **Ramps.** The contract's polyline of a pixel is a sum of ramps: an event of change ``c`` at
  a pixel whose previous knot time is ``t0`` adds the ramp of rise ``c`` over ``[h, t]``,
  ``h = max(t0, t - D)`` (``D``'s held knot; events at one time add ramps over the same
  interval, which sum to the merged knot's). A ramp's end comes at its event's time, so the
  ends arrive in time order (a ring); its start is either ``t - D`` (or ``t_start``), which
  also arrives in time order (a second ring), or the pixel's previous knot, whose end is
  still ahead of the horizon: the start's slope change is added to that end's. Per pixel, the
  loop keeps its last two knot times and their ends' places in the ring.
* **Sweep.** The slope changes before the horizon ``tau - D``, a merge of the two rings in
  time order; each output region keeps its value, slope, pending jump and reference index,
  and is advanced to a change's time when one comes (the reference rule on the piece, then
  the change), and to the horizon at the end. Each region also keeps its value's error
  (below), read only to decide a *doubt*.

The arithmetic is fixed point, the same whatever the chunks: each ramp's slope is
``round(c * 2**K / (t - h))`` units of ``2**-K`` levels per microsecond (a table over the
lengths up to ``D``: no division an event) and the ramp ends exactly at ``c * 2**K`` (a jump
of at most half a unit per microsecond of ramp), so a region's value is an exact integer at
every integer time. With ``A`` ramps active in a region, it is within ``E = A * D / 2`` units
of the exact polyline's. That error is known: a ramp's slope is off by
``delta = round(2**K / length) - 2**K / length`` (times ``c``), so the region's error grows at
the sum of its active ramps' deltas and drops back by each ramp's whole error when its end's
jump comes. The sweep keeps both in float64 (``error``, ``error_slope``: a few float additions
a change, none an event beyond the ring's one ``delta``). Where the integers cannot decide
what the package decides, a *doubt*: a value within ``E`` (plus the package's snap, ``SNAP``
thresholds) of a level, or a crossing within ``E / (|slope| - A / 2)`` (plus the package's
half-tick tolerance) of a half tick, it applies the package's rules
(:func:`~evdown_torch.transforms.functional.reference.level_index`'s snap,
:func:`~evdown_torch.transforms.functional.estimation.knots.piece_time`'s rounding) to
``value - error`` and ``slope - error_slope``, within about ``1e-12`` units (``1e-22``
levels) of the exact ones. So it decides as the package's float arithmetic does (itself
within about ``1e-15`` levels), except where the exact value lies that close to the edge of
those tolerances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.estimation.knots import HALF_TOLERANCE, RELATIVE_ERROR
from evdown_torch.transforms.functional.reference import SNAP

__all__ = ["LEVEL_BITS", "RampSession", "RampSettings"]

K = 32
_HALF = 0.5 + HALF_TOLERANCE


@compiled_loop
def _ramps(
    xs: np.ndarray, ys: np.ndarray, ts: np.ndarray, ps: np.ndarray, width: int,
    column: np.ndarray, row: np.ndarray, out_w: int, delay: int, one: int, slopes: np.ndarray,
    deltas: np.ndarray, t_start: int, pixels: np.ndarray, ends: int, e_t: np.ndarray,
    e_region: np.ndarray, e_slope: np.ndarray, e_jump: np.ndarray, e_active: np.ndarray,
    e_delta: np.ndarray, starts: int, s_t: np.ndarray, s_region: np.ndarray,
    s_slope: np.ndarray, s_delta: np.ndarray, mask: int, head_e: int, head_s: int,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """Each event's ramp: its end, and its start as a change of its own or added to one.

    A ramp ends at its event's time ``t``: the ends come in time order (ring ``e_*``).
    It starts at ``h = max(t0, t - D)``: at ``t - D`` (or ``t_start``) when the pixel was
    idle for ``D``, which also comes in time order (ring ``s_*``); else at the pixel's
    previous knot ``t0``, whose end is still ahead of the horizon: its slope change is
    added to that end's. An event at its pixel's last knot time adds to that knot's ramp.

    ``slopes``: ``round(2**K / length)`` for each ramp length up to ``D`` (a table: no
    division an event); ``deltas``: ``slopes - 2**K / length`` (float64), the slope's
    rounding, whose sums the sweep keeps (``e_delta``, ``s_delta``). ``pixels``:
    ``(W * H, 5)``, each pixel's last knot time, the one before, their ends' places in
    the ring (-1: none) and the pixel's level. ``e_active``: the change of the region's
    count of active ramps (a start ring entry is one ramp).

    Returns the rings' new tails ``(ends, starts)``.

    Raises:
        ValueError: when a ring is full (its oldest change not yet swept, ``head_*``).
    """
    # Every index is cast to unsigned (each is non-negative: ``_numba``, "Unsigned indices").
    for i in range(xs.shape[0]):
        x, y, t = np.int64(xs[i]), np.int64(ys[i]), ts[i]
        c = 1 if ps[i] else -1
        pixel = np.uint64(y * width + x)
        r = row[np.uint64(y)] * out_w + column[np.uint64(x)]
        pixels[pixel, 4] += c
        if t > pixels[pixel, 0] or pixels[pixel, 2] < 0:  # a new knot: a new end
            pixels[pixel, 1], pixels[pixel, 3] = pixels[pixel, 0], pixels[pixel, 2]
            pixels[pixel, 0], pixels[pixel, 2] = t, ends
            if ends - head_e > mask:
                raise ValueError("the ramps' ends ring is full (RampSession.reserve not called)")
            k = np.uint64(ends & mask)
            e_t[k], e_region[k] = t, r
            e_slope[k], e_jump[k], e_active[k], e_delta[k] = 0, 0, 0, 0.0
            ends += 1
        t0 = pixels[pixel, 1]
        h = max(t0, t - delay)
        length = t - h  # 0 for a first event at t_start: a jump, no ramp
        slope = c * slopes[np.uint64(length)]  # round(2**K / length), 0 for a jump
        delta = c * deltas[np.uint64(length)]
        end = np.uint64(pixels[pixel, 2] & mask)
        e_slope[end] -= slope
        e_jump[end] += c * one - slope * length
        e_delta[end] -= delta
        if length:
            e_active[end] -= 1
        if t0 > t - delay and pixels[pixel, 3] >= 0:
            before = np.uint64(pixels[pixel, 3] & mask)
            e_slope[before] += slope
            e_active[before] += 1
            e_delta[before] += delta
        elif length:  # (a ramp whose slope rounds to 0 still starts: its error, its count)
            if starts - head_s > mask:
                raise ValueError("the ramps' starts ring is full (RampSession.reserve not called)")
            k = np.uint64(starts & mask)
            s_t[k], s_region[k] = max(t - delay, t_start), r
            s_slope[k], s_delta[k] = slope, delta
            starts += 1
    return ends, starts


@compiled_loop
def _sweep(
    head_e: int, tail_e: int, e_t: np.ndarray, e_region: np.ndarray, e_slope: np.ndarray,
    e_jump: np.ndarray, e_active: np.ndarray, e_delta: np.ndarray, head_s: int, tail_s: int,
    s_t: np.ndarray, s_region: np.ndarray, s_slope: np.ndarray, s_delta: np.ndarray, mask: int,
    horizon: int, value: np.ndarray, slope_sum: np.ndarray, since: np.ndarray,
    pending: np.ndarray, q: np.ndarray, active: np.ndarray, error: np.ndarray,
    error_slope: np.ndarray, q_change: np.ndarray, t_change: np.ndarray, t_start: int,
    delay: int, levels: np.ndarray, b: int, out_r: np.ndarray, out_t: np.ndarray,
    out_on: np.ndarray, counts: np.ndarray, headroom: int,
) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """The slope changes before the horizon, in time order (a merge of the two rings).

    Each region is advanced lazily: to a change's time when one comes (its pending jump
    at its own time, then its ramp), and to the horizon at the end. Beside its integer
    value, each region keeps that value's error (float64, ``error``: the active ramps'
    slope roundings times their elapsed times, exactly 0 for a ramp at its end once its
    jump is in) and the error's slope (``error_slope``: the sum of the roundings). A
    doubt (see the module) is decided on ``value - error`` by the package's rules.
    ``levels``: each region's level spacing in units (``a * n_r * 2**K``, threshold
    ``a / b``, ``n_r`` pixels). ``counts``: the doubts decided this way, at a level and at
    a half tick, added to. ``headroom``: the largest value allowed (``Settings``).
    ``q_change``, ``t_change``: each region's reference index after its last change
    swept, its jump included, and that change's time (the package's ``q`` after the
    region's last breakpoint before the horizon, which a
    :class:`~evdown_torch.transforms.functional.estimation.stream.WindowState` keeps).

    Returns the rings' new heads and the outputs' count, -1 where the outputs' buffer is
    full (the session is then spent: :meth:`RampSession.__call__`).

    Raises:
        ValueError: when a region's value leaves the headroom.
    """
    n_out = 0
    regions = value.shape[0]
    final = 0  # after the rings: each region in turn, to the horizon
    next_end = e_t[np.uint64(head_e & mask)] if head_e < tail_e else horizon
    next_start = s_t[np.uint64(head_s & mask)] if head_s < tail_s else horizon
    while final < regions:
        if next_end < horizon or next_start < horizon:
            if next_end <= next_start:
                k = np.uint64(head_e & mask)
                t, r, d_slope, d_jump = next_end, e_region[k], e_slope[k], e_jump[k]
                d_active, d_delta = e_active[k], e_delta[k]
                head_e += 1
                next_end = e_t[np.uint64(head_e & mask)] if head_e < tail_e else horizon
            else:
                k = np.uint64(head_s & mask)
                t, r, d_slope, d_jump = next_start, s_region[k], s_slope[k], 0
                d_active, d_delta = 1, s_delta[k]
                head_s += 1
                next_start = s_t[np.uint64(head_s & mask)] if head_s < tail_s else horizon
        else:
            t, r, d_slope, d_jump, d_active, d_delta = horizon, final, 0, 0, 0, 0.0
            final += 1
        region = np.uint64(r)  # (an unsigned index, as in _ramps)
        t_now = since[region]
        if t > t_now:
            v, qr, sl = value[region], q[region], slope_sum[region]
            jump, n_active = pending[region], active[region]
            err, err_slope, level = error[region], error_slope[region], levels[region]
            bound = n_active * delay // 2 + 1  # E, with a unit to spare
            near_level = b * bound + np.int64(SNAP * level) + 2
            for piece in range(2):  # the jump at t_now, then the ramp to t
                if piece == 0:
                    if jump == 0:
                        continue
                    # The ends' jumps cancel their ramps' errors; at t_start, the
                    # first events' jumps are the curve's own.
                    v1, err1, t_end = v + jump, err + jump if t_now > t_start else err, t_now
                else:
                    if sl == 0 and err_slope == 0.0:
                        break  # flat (a fixed slope of 0 over moving ramps is not)
                    v1, err1, t_end = v + sl * (t - t_now), err + err_slope * (t - t_now), t
                if v1 > headroom or v1 < -headroom:
                    raise ValueError("a region's sum of levels left the integers' headroom")
                scaled = b * v1
                if (qr - 1) * level + near_level < scaled < (qr + 1) * level - near_level:
                    v, err = v1, err1  # off levels q - 1 and q + 1 by more than E: q stays
                    continue
                m = scaled // level
                off = scaled - m * level
                on = off == 0
                if n_active > 0 and min(off, level - off) <= near_level:
                    counts[0] += 1
                    within = (off - b * err1) / level  # u - m, u on value - error
                    nearest = np.floor(within + 0.5)
                    on = abs(within - nearest) <= SNAP
                    m += np.int64(nearest) if on else np.int64(np.floor(within))
                q_new = m if on else min(max(qr, m), m + 1)
                while qr != q_new:
                    d = 1 if q_new > qr else -1
                    qr += d
                    if n_out == out_t.shape[0]:
                        return head_e, head_s, -1  # (the buffer's size: the caller's bound)
                    out_t[n_out], out_r[n_out], out_on[n_out] = t_end, r, d > 0
                    n_out += 1
                    if piece == 0 or (on and qr == q_new):
                        continue  # at the move's end
                    span = t - t_now
                    num, den = qr * level - b * v, b * sl
                    spare = abs(sl) - n_active / 2
                    near_half = spare <= 0
                    if not near_half:
                        offset = (2 * num + den) // (2 * den)  # floor(num / den + 1/2)
                        half = abs((num / den) % 1.0 - 0.5)
                        tolerance = HALF_TOLERANCE + RELATIVE_ERROR * span + 1e-9
                        near_half = half <= bound / spare + tolerance
                    if near_half:
                        counts[1] += 1
                        exact_slope = b * (sl - err_slope)
                        if exact_slope == 0.0:  # a flat piece: at the move's end
                            offset = span
                        else:
                            ratio = (num + b * err) / exact_slope
                            offset = np.int64(np.floor(ratio + _HALF
                                                       + RELATIVE_ERROR * span))
                    out_t[n_out - 1] = t_now + min(max(offset, 0), span)
                v, err = v1, err1
                if piece == 0:  # the jump is at the region's last change
                    q_change[region] = qr
            value[region], since[region], q[region] = v, t, qr
            pending[region], error[region] = 0, err
        if t < horizon:  # a change (the advance to the horizon is not one)
            q_change[region], t_change[region] = q[region], t
        slope_sum[region] += d_slope
        pending[region] += d_jump
        active[region] += d_active
        error_slope[region] += d_delta
    return head_e, head_s, n_out


#: A region's sum of levels must stay within ``n_r * 2**LEVEL_BITS`` (the integers' headroom).
LEVEL_BITS = 20


@dataclass(frozen=True)
class RampSettings:
    """The ramps' geometry and integers, for the loops and the eager twin alike.

    Build it with :meth:`of`. Attributes: ``width`` (``W``), ``out_w``; ``column``, ``row``
    (``(W,)``, ``(H,)`` int64, each pixel column's and row's region); ``pixels`` (``(R,)``
    int64 ``n_r``); ``a``, ``b`` (the threshold ``a / b``); ``delay`` (``D``, time units);
    ``k`` (the fixed point's bits: 32, or less where ``b * n_r * 2**(k + LEVEL_BITS)`` would
    not fit in 62 bits); ``one`` (``2**k``); ``levels`` (``(R,)`` int64 ``a * n_r * 2**k``);
    ``slopes`` (``(D + 1,)`` int64 ``round(2**k / length)``, 0 at 0) and ``deltas``
    (float64 ``slopes - 2**k / length``, their rounding); ``headroom`` (the largest value
    allowed, ``max n_r * 2**(level_bits + k)`` units: beyond it the loops raise).
    """

    width: int
    out_w: int
    column: np.ndarray
    row: np.ndarray
    pixels: np.ndarray
    a: int
    b: int
    delay: int
    k: int
    one: int
    levels: np.ndarray
    slopes: np.ndarray
    deltas: np.ndarray
    headroom: int

    @classmethod
    def of(cls, sensor_size: tuple[int, int, int], factor: tuple[int, int],
           threshold: tuple[int, int], delay: int, level_bits: int = LEVEL_BITS,
           ) -> RampSettings:
        """The settings for a sensor, a factor ``(fx, fy)``, a threshold ``(a, b)`` and ``D``.

        Edge regions of a sensor the factor does not divide are smaller (``n_r``). A region's
        sum of levels may reach ``n_r * 2**level_bits`` in size.

        Raises:
            ValueError: where even ``k = 8`` would not fit.

        Example:
            >>> settings = RampSettings.of((5, 4, 2), (2, 2), (1, 4), 1000)
            >>> settings.pixels.tolist(), settings.k, int(settings.slopes[3])
            ([4, 4, 2, 4, 4, 2], 32, 1431655765)
        """
        width, height, _ = sensor_size
        (fx, fy), (a, b) = factor, threshold
        column = np.arange(width, dtype=np.int64) // fx
        row = np.arange(height, dtype=np.int64) // fy
        pixels = np.outer(np.bincount(row), np.bincount(column)).reshape(-1).astype(np.int64)
        k = min(K, 62 - level_bits - b.bit_length() - int(pixels.max()).bit_length())
        if k < 8:
            raise ValueError(f"threshold {a}/{b} with {int(pixels.max())} pixels a region "
                             "leaves the fixed point under 8 bits")
        one = 1 << k
        length = np.arange(delay + 1, dtype=np.int64)
        slopes = (one + length // 2) // np.maximum(length, 1)
        slopes[0] = 0
        deltas = slopes - float(one) / np.maximum(length, 1)
        deltas[0] = 0.0
        return cls(width, -(-width // fx), column, row, pixels, a, b, delay, k, one,
                   (a * pixels) << k, slopes, deltas, int(pixels.max()) << (level_bits + k))


def _by_time_then_region(region: np.ndarray, t: np.ndarray, on: np.ndarray, regions: int,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The crossings sorted by time, a tie in region order, else in the order found.

    One stable sort of ``(t - t_min) * regions + region`` where it fits in int64 (the sweep
    finds them nearly in time order, which the stable sort's runs take), else two keys.
    """
    if t.shape[0] == 0:
        return region, t, on
    low = int(t.min())
    if int(t.max()) - low < (1 << 62) // regions:
        order = np.argsort((t - low) * regions + region, kind="stable")
    else:
        order = np.lexsort((region, t))
    return region[order], t[order], on[order]


def _after_returned(region: np.ndarray, returned: np.ndarray) -> np.ndarray:
    """``(C,)`` bool: the crossings, each region's in time order, after its first ``returned``.

    Example:
        >>> _after_returned(np.array([3, 1, 3, 3, 1]), np.array([0, 1, 0, 2])).tolist()
        [False, False, False, True, True]
    """
    order = np.argsort(region, kind="stable")
    by_region = region[order]
    first = np.flatnonzero(np.r_[True, by_region[1:] != by_region[:-1]])
    rank = np.arange(region.shape[0]) - np.repeat(first, np.diff(np.r_[first, region.shape[0]]))
    after = np.empty(region.shape[0], np.bool_)
    after[order] = rank >= returned[by_region]
    return after


class RampSession:
    """A bounded-delay stream as ramps: ``__call__(chunk)`` returns the decided events.

    Args:
        t_start: the stream's first time.
        max_events: the chunk size to size the rings for at first (they grow to fit the
            events of each chunk and those ahead of the horizon).
        settings: :class:`RampSettings`.

    The returned events are those earlier than the horizon ``tau - D`` (``tau``: the chunk's
    last time) not returned before, as the package's windowed session returns them. ``counts``:
    the doubts decided on the corrected value so far, ``[at a level, at a half tick]``.
    """

    def __init__(self, t_start: int, max_events: int, settings: RampSettings) -> None:
        self.settings = settings
        regions = settings.pixels.shape[0]
        self.pixels = np.empty((settings.width * settings.row.shape[0], 5), np.int64)
        size = 1 << int(4 * max_events).bit_length()  # a chunk's changes and those ahead
        self.mask = size - 1
        # Written now, not on first use: a page fault in a timed chunk is no loop's cost.
        # ends: t, region, slope, jump, active, delta; starts: t, region, slope, delta.
        self.ends = [np.full(size, 0, np.float64 if k == 5 else np.int64) for k in range(6)]
        self.starts = [np.full(size, 0, np.float64 if k == 3 else np.int64) for k in range(4)]
        self.regions = [np.empty(regions, np.float64 if k in (6, 7) else np.int64)
                        for k in range(10)]
        # value, slope, since, pending jump, q, active ramps, error, error's slope, q after
        # the last change and its time
        self.out = (np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size, np.bool_))
        self.counts = np.zeros(2, np.int64)
        self.reset(t_start)

    def reset(self, t_start: int) -> None:
        """A new stream from ``t_start`` (the arrays kept: rings, outputs, tables)."""
        self.t_start = t_start
        self.pixels[:, :2], self.pixels[:, 2:4], self.pixels[:, 4] = t_start, -1, 0
        self.head_e = self.tail_e = self.head_s = self.tail_s = 0
        for k, column in enumerate(self.regions):
            column[:] = t_start if k in (2, 9) else 0
        self.horizon = self.t_last = t_start
        # A session carrying on from the package's state
        # (:func:`~.linear_ramps_state.ramp_session`): the state's horizon, and how many
        # crossings of each region's piece across it its steps returned (its ``returned``).
        self.returned: tuple[int, np.ndarray] | None = None
        self.at_horizon = tuple(np.empty(0, dtype) for dtype in (np.int64, np.int64, np.bool_))
        self.recent = tuple(np.empty(0, np.int64) for _ in range(4))

    def reserve(self, events: int) -> None:
        """Rings that hold ``events`` more changes beside those not swept yet (grown here).

        Each event adds at most one end and one start; a ring's entries keep their places
        (counters, taken modulo the ring's size).
        """
        need = max(self.tail_e - self.head_e, self.tail_s - self.head_s) + events
        if need <= self.mask:
            return
        size = 1 << int(need).bit_length()
        mask = size - 1
        for ring, head, tail in ((self.ends, self.head_e, self.tail_e),
                                 (self.starts, self.head_s, self.tail_s)):
            at = np.arange(head, tail, dtype=np.int64)
            for k, column in enumerate(ring):
                grown = np.zeros(size, column.dtype)
                grown[at & mask] = column[at & self.mask]
                ring[k] = grown
        self.mask = mask

    def __call__(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The events decided by a chunk, as ``(x, y, t, on)`` columns sorted by ``t``.

        Args:
            x: ``(N,)`` integer columns, within the sensor (not checked here).
            y: ``(N,)`` integer rows.
            t: ``(N,)`` int64 times in stable time order, none before the last chunk's.
            p: ``(N,)`` bool polarities.

        Returns:
            ``(x, y, t, on)``: int64, int64, int64 and bool, sorted by ``t`` (a tie in
            region order, as the windowed session); ``None`` where the crossings outgrew the
            outputs' buffer (the session is then spent; the caller solves the chunk as a
            window instead). The buffer holds the bound below, which holds where each change
            of the rings is one ramp; changes that merge many events of a pixel and time
            (hundreds a microsecond) or a seeded state's whole levels can pass it.

        Raises:
            ValueError: when a region's value leaves the headroom (the session is then spent).
        """
        settings = self.settings
        self.reserve(len(t))
        self.tail_e, self.tail_s = _ramps(
            x, y, t, p, settings.width, settings.column, settings.row,
            settings.out_w, settings.delay, settings.one, settings.slopes, settings.deltas,
            self.t_start, self.pixels, self.tail_e, *self.ends, self.tail_s, *self.starts,
            self.mask, self.head_e, self.head_s)
        if len(t):
            self.horizon = max(self.horizon, int(t[-1]) - settings.delay)
        # Each ramp moves its region's level by one pixel level, at most ceil(b / (a * n_r))
        # thresholds; each piece may add two for a level it touches.
        pending = self.tail_e - self.head_e + self.tail_s - self.head_s + len(settings.pixels)
        per_change = -(-settings.b // (settings.a * int(settings.pixels.min()))) + 2
        if pending * per_change > len(self.out[0]):
            self.out = (np.empty(pending * per_change, np.int64),
                        np.empty(pending * per_change, np.int64),
                        np.empty(pending * per_change, np.bool_))
        self.head_e, self.head_s, n_out = _sweep(
            self.head_e, self.tail_e, *self.ends, self.head_s, self.tail_s, *self.starts,
            self.mask, self.horizon, *self.regions, self.t_start, settings.delay,
            settings.levels, settings.b, *self.out, self.counts, settings.headroom)
        if n_out < 0:
            return None
        out_r, out_t, out_on = (column[:n_out] for column in self.out)
        if self.returned is not None:  # the first chunk after a state: as the package drops
            # the crossings it returned, by their count, and raises the rest to the horizon
            # (the sweep found them all: it went from each region's last change before that
            # horizon to this one, no earlier)
            seeded_at, returned = self.returned
            new = _after_returned(out_r, returned)
            out_r, out_t, out_on = out_r[new], np.maximum(out_t[new], seeded_at), out_on[new]
            self.returned = None
        # Crossings at the horizon itself are returned once the horizon passes them, as the
        # package's session returns them (only events earlier than its horizon are decided).
        held_r, held_t, held_on = self.at_horizon
        out_r = np.concatenate([held_r, out_r])
        out_t = np.concatenate([held_t, out_t])
        out_on = np.concatenate([held_on, out_on])
        out_r, out_t, out_on = _by_time_then_region(out_r, out_t, out_on, len(settings.pixels))
        cut = int(np.searchsorted(out_t, self.horizon))
        self.at_horizon = (out_r[cut:], out_t[cut:], out_on[cut:])
        out_r, out_t, out_on = out_r[:cut], out_t[:cut], out_on[:cut]
        # The events from D before the horizon on, as ``(x, y, t, change)`` columns: the
        # knots the package's state keeps are among them (:func:`.linear_ramps_state.\
        # window_state` reads them).
        since = self.horizon - settings.delay
        at = int(np.searchsorted(self.recent[2], since))
        first = int(np.searchsorted(t, since))
        added = (x[first:], y[first:], t[first:], 2 * p[first:].astype(np.int64) - 1)
        self.recent = tuple(np.concatenate([old[at:], part], dtype=np.int64)
                            for old, part in zip(self.recent, added, strict=True))
        if len(t):
            self.t_last = int(t[-1])
        out_w = settings.out_w
        return out_r % out_w, out_r // out_w, out_t, out_on
