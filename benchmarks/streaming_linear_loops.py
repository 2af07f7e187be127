"""The streaming LinearEstimation design's compiled loops and its session (an estimate's).

:mod:`benchmarks.streaming_linear_estimate` times them against the package's session; this
module holds the design itself: two passes over each chunk, no window and no sort.

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
  the change), and to the horizon at the end. The sweep also keeps each pixel's level and
  current segment (start, end, rise), read only to decide a *doubt* (below).

The arithmetic is fixed point, the same whatever the chunks: each ramp's slope is
``round(c * 2**K / (t - h))`` units of ``2**-K`` levels per microsecond (a table over the
lengths up to ``D``: no division an event) and the ramp ends exactly at ``c * 2**K`` (a jump
of at most half a unit per microsecond of ramp), so a region's value is an exact integer at
every integer time. With ``A`` ramps active in a region, it is within ``E = A * D / 2`` units
of the exact polyline's. Where that cannot decide what the package decides, a *doubt*: a
value within ``E`` (plus the package's snap, ``SNAP`` thresholds) of a level, or a crossing
within ``E / (|slope| - A / 2)`` (plus the package's half-tick tolerance) of a half tick, the
sweep evaluates the region's pixels' segments at that time (exact integer parts, a float
remainder: :func:`compile_loops`'s ``exact_at``) and applies the package's rules to it
(:func:`~evdown_torch.transforms.functional.reference.level_index`'s snap,
:func:`~evdown_torch.transforms.functional.estimation.knots.piece_time`'s rounding). So it
decides as the package's float arithmetic does, except where the exact value lies within
float error (about ``1e-15`` of a level) of the edge of those tolerances.
"""

from __future__ import annotations

import numpy as np

from evdown_torch.bench.realtime import REALTIME_MAX_DELAY_US
from evdown_torch.transforms.functional.estimation.knots import HALF_TOLERANCE, RELATIVE_ERROR
from evdown_torch.transforms.functional.reference import SNAP

try:
    import numba
except ImportError:  # pragma: no cover - depends on the machine
    numba = None

SENSOR = (128, 128, 2)
FACTOR = 4
THRESHOLD = (1, 4)  # 0.25 as a / b
K = 32
_HALF = 0.5 + HALF_TOLERANCE


def compile_loops() -> dict:
    """The loop's two passes, compiled (Numba's ``njit``)."""
    if numba is None:
        raise RuntimeError("the compiled loops need numba (pip install numba)")

    @numba.njit(nogil=True)
    def ramps(xs, ys, ts, ps, width, delay, slopes, t_start, pixels, ends, e_t, e_slope, e_jump,
              e_active, e_pixel, e_rise, e_next_t, e_next_rise, starts, s_t, s_pixel, s_end,
              s_rise, mask):  # pragma: no cover - compiled
        """Each event's ramp: its end, and its start as a change of its own or added to one.

        A ramp ends at its event's time ``t``: the ends come in time order (ring ``e_*``).
        It starts at ``h = max(t0, t - D)``: at ``t - D`` (or ``t_start``) when the pixel was
        idle for ``D``, which also comes in time order (ring ``s_*``); else at the pixel's
        previous knot ``t0``, whose end is still ahead of the horizon: its slope change is
        added to that end's. An event at its pixel's last knot time adds to that knot's ramp.

        ``slopes``: ``round(2**K / length)`` for each ramp length up to ``D`` (a table: no
        division an event). ``pixels``: ``(W * H, 4)``, each pixel's last knot time, the one
        before, and their ends' places in the ring (-1: none). ``e_active``: the
        change of the region's count of active ramps (for the doubt's bound). For the
        sweep's segments: ``e_pixel``, ``e_rise`` (the knot's change of level), ``e_next_t``
        and ``e_next_rise`` (the segment that starts at the knot: its end and rise; -1 and 0
        while none), ``s_pixel``, ``s_end``, ``s_rise`` (a held knot's segment, one event's:
        its slope is ``s_rise * slopes[s_end - s_t]``, one ramp).

        Returns the rings' new tails ``(ends, starts)``.
        """
        one = np.int64(1) << K
        for i in range(xs.shape[0]):
            x, y, t = np.int64(xs[i]), np.int64(ys[i]), ts[i]
            c = 1 if ps[i] else -1
            pixel = y * width + x
            if t > pixels[pixel, 0] or pixels[pixel, 2] < 0:  # a new knot: a new end
                pixels[pixel, 1], pixels[pixel, 3] = pixels[pixel, 0], pixels[pixel, 2]
                pixels[pixel, 0], pixels[pixel, 2] = t, ends
                k = ends & mask
                e_t[k], e_pixel[k] = t, pixel
                e_slope[k], e_jump[k], e_active[k], e_rise[k] = 0, 0, 0, 0
                e_next_t[k], e_next_rise[k] = -1, 0
                ends += 1
            t0 = pixels[pixel, 1]
            h = max(t0, t - delay)
            length = t - h  # 0 for a first event at t_start: a jump, no ramp
            slope = c * slopes[length]  # round(2**K / length), 0 for a jump
            end = pixels[pixel, 2] & mask
            e_slope[end] -= slope
            e_jump[end] += c * one - slope * length
            e_rise[end] += c
            if length:
                e_active[end] -= 1
            if t0 > t - delay and pixels[pixel, 3] >= 0:
                before = pixels[pixel, 3] & mask
                e_slope[before] += slope
                e_active[before] += 1
                e_next_t[before] = t
                e_next_rise[before] += c
            elif slope != 0:
                k = starts & mask
                s_t[k], s_pixel[k], s_end[k], s_rise[k] = max(t - delay, t_start), pixel, t, c
                starts += 1
        return ends, starts

    @numba.njit(nogil=True)
    def exact_at(r, x2, members, segments):  # pragma: no cover - compiled
        """Region ``r``'s sum of levels at ``x2 / 2`` from its pixels' segments.

        Returns ``(whole, rest, slope)``: the exact integer part, the remainder (float64,
        0.0 exactly where the sum is an integer) and the sum's slope (levels per tick).
        """
        whole, rest, slope = np.int64(0), 0.0, 0.0
        for i in range(members.shape[1]):
            pixel = members[r, i]
            whole += segments[pixel, 0]
            rise = segments[pixel, 3]
            if rise != 0:
                span = segments[pixel, 2] - segments[pixel, 1]
                num, den = rise * (x2 - 2 * segments[pixel, 1]), 2 * span
                part = num // den
                whole += part
                rest += (num - part * den) / den
                slope += rise / span
        return whole, rest, slope

    @numba.njit(nogil=True)
    def sweep(head_e, tail_e, e_t, e_slope, e_jump, e_active, e_pixel, e_rise, e_next_t,
              e_next_rise, head_s, tail_s, s_t, s_pixel, s_end, s_rise, mask, horizon, region_of,
              slopes, value, slope_sum, since, pending, q,
              active, segments, members, delay, level, a, b, out_r, out_t, out_on,
              counts):  # pragma: no cover - compiled
        """The slope changes before the horizon, in time order (a merge of the two rings).

        Each region is advanced lazily: to a change's time when one comes (its pending jump
        at its own time, then its ramp), and to the horizon at the end. A doubt (see the
        module) is decided on ``exact_at``'s value by the package's rules. ``segments``:
        ``(W * H, 4)``, each pixel's level and current segment ``(start, end, rise)``;
        ``members``: ``(regions, n)`` the pixels of each region. ``counts``: the doubts
        decided this way, at a level and at a half tick, added to.

        Returns the rings' new heads and the outputs' count.
        """
        n_out = 0
        regions, n = value.shape[0], members.shape[1]
        per_level = b / (n * a)
        snap_units = np.int64(SNAP * level) + 2
        final = 0  # after the rings: each region in turn, to the horizon
        next_end = e_t[head_e & mask] if head_e < tail_e else horizon
        next_start = s_t[head_s & mask] if head_s < tail_s else horizon
        while final < regions:
            pixel, rise, to, next_rise, from_end = -1, 0, -1, 0, True
            if next_end < horizon or next_start < horizon:
                if next_end <= next_start:
                    k = head_e & mask
                    t, pixel, d_slope, d_jump = next_end, e_pixel[k], e_slope[k], e_jump[k]
                    d_active, rise = e_active[k], e_rise[k]
                    to, next_rise = e_next_t[k], e_next_rise[k]
                    head_e += 1
                    next_end = e_t[head_e & mask] if head_e < tail_e else horizon
                else:
                    k = head_s & mask
                    t, pixel, to, next_rise = next_start, s_pixel[k], s_end[k], s_rise[k]
                    d_slope, d_jump, d_active = next_rise * slopes[to - t], 0, 1
                    from_end = False
                    head_s += 1
                    next_start = s_t[head_s & mask] if head_s < tail_s else horizon
                r = region_of[pixel]
            else:
                t, r, d_slope, d_jump, d_active = horizon, final, 0, 0, 0
                final += 1
            t_now = since[r]
            if t > t_now:
                v, qr, sl, jump, n_active = value[r], q[r], slope_sum[r], pending[r], active[r]
                error = n_active * delay // 2 + 1  # E, with a unit to spare
                near_level = b * error + snap_units
                for piece in range(2):  # the jump at t_now, then the ramp to t
                    if piece == 0:
                        if jump == 0:
                            continue
                        v1, t_end = v + jump, t_now
                    else:
                        if sl == 0:
                            break
                        v1, t_end = v + sl * (t - t_now), t
                    scaled = b * v1
                    if (qr - 1) * level + near_level < scaled < (qr + 1) * level - near_level:
                        v = v1  # off levels q - 1 and q + 1 by more than the doubt: q stays
                        continue
                    m = scaled // level
                    off = scaled - m * level
                    on = off == 0
                    if n_active > 0 and min(off, level - off) <= near_level:
                        counts[0] += 1
                        whole, rest, _ = exact_at(r, 2 * t_end, members, segments)
                        if rest == 0.0:
                            m = (whole * b) // (n * a)
                            on = m * (n * a) == whole * b
                        else:
                            u = (whole + rest) * per_level
                            nearest = np.floor(u + 0.5)
                            on = abs(u - nearest) <= SNAP
                            m = np.int64(nearest) if on else np.int64(np.floor(u))
                    q_new = m if on else min(max(qr, m), m + 1)
                    while qr != q_new:
                        d = 1 if q_new > qr else -1
                        qr += d
                        out_t[n_out], out_r[n_out], out_on[n_out] = t_end, r, d > 0
                        n_out += 1
                        if piece == 0 or (on and qr == q_new):
                            continue  # at the move's end
                        span = t - t_now
                        num, den = qr * level - b * v, b * sl
                        offset = (2 * num + den) // (2 * den)  # floor(num / den + 1/2)
                        spare = abs(sl) - n_active / 2
                        half = abs((num / den) % 1.0 - 0.5)
                        tolerance = HALF_TOLERANCE + RELATIVE_ERROR * span + 1e-9
                        if spare <= 0 or half <= error / spare + tolerance:
                            counts[1] += 1
                            whole, rest, slope = exact_at(r, 2 * t_now, members, segments)
                            target = (qr * n * a) / b
                            if slope == 0.0:  # a flat piece: at the move's end
                                offset = span
                            else:
                                ratio = ((target - whole) - rest) / slope
                                offset = np.int64(np.floor(ratio + _HALF
                                                           + RELATIVE_ERROR * span))
                        out_t[n_out - 1] = t_now + min(max(offset, 0), span)
                    v = v1
                value[r], since[r], q[r], pending[r] = v, t, qr, 0
            slope_sum[r] += d_slope
            pending[r] += d_jump
            active[r] += d_active
            if pixel >= 0:  # the pixel's segment from here
                if from_end:
                    segments[pixel, 0] += rise
                    segments[pixel, 3] = 0
                if to >= 0:
                    segments[pixel, 1], segments[pixel, 2] = t, to
                    segments[pixel, 3] += next_rise
        return head_e, head_s, n_out

    return {"ramps": ramps, "sweep": sweep}


def region_members() -> np.ndarray:
    """``(regions, FACTOR**2)`` int64: each output region's pixels (``y * W + x``), ascending."""
    width, height, _ = SENSOR
    pixel_y, pixel_x = np.divmod(np.arange(width * height), width)
    region = (pixel_y // FACTOR) * (width // FACTOR) + pixel_x // FACTOR
    return np.argsort(region, kind="stable").reshape(-1, FACTOR * FACTOR)


class StreamingLinear:
    """The design as a session: ``__call__(chunk)`` returns the decided events, sorted.

    Args:
        loops: :func:`compile_loops`'s.
        t_start: the stream's first time (microseconds).
        max_events: the most events a chunk holds; the rings hold four times as many changes
            (the replay's 10 ms chunks against ``D = 1 ms``: room to spare; a session fed
            chunks much shorter than ``D`` needs ``max_events`` of the events within ``D``).

    ``counts``: the doubts decided on the pixels' segments so far, ``[at a level, at a half
    tick]``.
    """

    def __init__(self, loops: dict, t_start: int, max_events: int) -> None:
        self.loops = loops
        width, height, _ = SENSOR
        self.out_w, out_h = width // FACTOR, height // FACTOR
        regions = self.out_w * out_h
        self.members = region_members()
        self.region_of = np.empty(width * height, np.int64)
        self.region_of[self.members] = np.arange(regions)[:, None]
        self.t_start = t_start
        length = np.arange(REALTIME_MAX_DELAY_US + 1, dtype=np.int64)
        self.slopes = ((1 << K) + length // 2) // np.maximum(length, 1)
        self.slopes[0] = 0
        self.pixels = np.full((width * height, 4), t_start, np.int64)
        self.pixels[:, 2:] = -1
        self.segments = np.zeros((width * height, 4), np.int64)  # level, start, end, rise
        size = 1 << int(4 * max_events).bit_length()  # a chunk's changes and those ahead
        self.mask = size - 1
        # Written now, not on first use: a page fault in a timed chunk is no loop's cost.
        self.ends = [np.full(size, 0, np.int64) for _ in range(8)]
        self.starts = [np.full(size, 0, np.int64) for _ in range(4)]
        self.head_e = self.tail_e = self.head_s = self.tail_s = 0
        self.regions = [np.zeros(regions, np.int64), np.zeros(regions, np.int64),
                        np.full(regions, t_start, np.int64), np.zeros(regions, np.int64),
                        np.zeros(regions, np.int64), np.zeros(regions, np.int64)]
        # value, slope, since, pending jump, q, active ramps
        self.out = (np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size, np.bool_))
        self.counts = np.zeros(2, np.int64)
        self.horizon = t_start
        self.a, self.b = THRESHOLD
        self.level = self.a * FACTOR * FACTOR * (1 << K)

    def __call__(self, chunk: np.ndarray) -> np.ndarray:
        t = chunk["t"]
        self.tail_e, self.tail_s = self.loops["ramps"](
            chunk["x"], chunk["y"], t, chunk["p"], SENSOR[0], REALTIME_MAX_DELAY_US, self.slopes,
            self.t_start, self.pixels, self.tail_e, *self.ends, self.tail_s, *self.starts,
            self.mask)
        self.horizon = max(self.horizon, int(t[-1]) - REALTIME_MAX_DELAY_US)
        self.head_e, self.head_s, n_out = self.loops["sweep"](
            self.head_e, self.tail_e, *self.ends, self.head_s, self.tail_s, *self.starts,
            self.mask, self.horizon, self.region_of, self.slopes, *self.regions, self.segments,
            self.members, REALTIME_MAX_DELAY_US, self.level, self.a, self.b, *self.out, self.counts)
        out_r, out_t, out_on = (column[:n_out] for column in self.out)
        order = np.argsort(out_t, kind="stable")
        result = np.empty(n_out, chunk.dtype)
        result["x"], result["y"] = out_r[order] % self.out_w, out_r[order] // self.out_w
        result["t"], result["p"] = out_t[order], out_on[order]
        return result
