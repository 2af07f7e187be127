"""What a streaming LinearEstimation loop would cost in the live replay: an estimate for a design.

Issue 38's goals 1 and 2 ask LinearEstimation with ``max_delay`` to keep up with the live
replay (the synthetic gesture recording retimed to 25 M events/s, 10 ms chunks, factor 4, one
thread), at 0.08 of the floor's rate or more. The package's compiled session solves a *window*
of knot events each chunk with the batch driver's arithmetic (every float as the eager kernel
computes it) and keeps the knot events the future needs: it groups and sorts every chunk's
events by region and by pixel, and it reaches about 0.04 of the floor (docs/benchmarks.md).
This script measures, on the same chunks and in the same run as the package's session and
the floor, a design that needs neither a window nor a sort: two passes over each chunk.

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
  the change), and to the horizon at the end.

The arithmetic is fixed point, the same whatever the chunks: each ramp's slope is
``round(c * 2**K / (t - h))`` units of ``2**-K`` levels per microsecond (a table over the
lengths up to ``D``: no division an event) and the ramp ends exactly at ``c * 2**K`` (a jump
of at most half a unit per microsecond of ramp), so a region's value is an exact integer at
every integer time and the level tests and rounded crossing times are integer operations.
That is not the package's arithmetic: the curve is within ``len * 2**-(K + 1)`` levels per
active ramp of the exact polyline (``K = 32``, ramps up to ``D = 1 ms``: about ``1e-7``
levels), so an event can move by a tick where the exact crossing lies on a half tick (the
contract rounds halves up; a curve a little off falls either side), or miss a touch of a
level. The script counts the events in one output and not the other, and pairs them one tick
apart. It also records the *doubts*, where the integers cannot tell (a value within their
error bound of a level, a crossing within it of a half tick: ``sweep``), which an exact
design would decide in exact arithmetic, and checks that every differing event lies within
a doubt's reach.

Its eager twin, :func:`design_whole`, takes the whole stream at once in vectorised torch (the
ramps from a sort by pixel, the changes summed per region and time, integer cumulative sums,
the package's reference rule over the moves); the script checks that it gives the session's
events, chunk boundaries notwithstanding.

So the figures price a design; they are no implementation (integer timestamps only, no
overflow checks, doubts recorded but not decided, the twin unoptimised).

Run: ``python benchmarks/streaming_linear_estimate.py [--events 13000000] [--chunks 50]``.
"""

from __future__ import annotations

import statistics
import time
from collections import Counter

import numpy as np
import torch

from evdown_torch._tensors import changes, run_index, segmented_cumsum, take, where_true
from evdown_torch.bench.estimates import estimate_replay
from evdown_torch.bench.floor import RegionFloor
from evdown_torch.bench.realtime import REALTIME_MAX_DELAY_US
from evdown_torch.transforms.functional.reference import move_crossings
from evdown_torch.transforms.registry import make_method

try:
    import numba
except ImportError:  # pragma: no cover - depends on the machine
    numba = None

SENSOR = (128, 128, 2)
FACTOR = 4
THRESHOLD = (1, 4)  # 0.25 as a / b
K = 32


def compile_loops() -> dict:
    """The loop's two passes, compiled (Numba's ``njit``)."""
    if numba is None:
        raise RuntimeError("the compiled loops need numba (pip install numba)")

    @numba.njit(nogil=True)
    def ramps(xs, ys, ts, ps, width, column, row, out_w, delay, slopes, t_start, pixels, ends, e_t,
              e_region, e_slope, e_jump, e_active, starts, s_t, s_region, s_slope, s_active,
              mask):  # pragma: no cover - compiled
        """Each event's ramp: its end, and its start as a change of its own or added to one.

        A ramp ends at its event's time ``t``: the ends come in time order (ring ``e_*``).
        It starts at ``h = max(t0, t - D)``: at ``t - D`` (or ``t_start``) when the pixel was
        idle for ``D``, which also comes in time order (ring ``s_*``); else at the pixel's
        previous knot ``t0``, whose end is still ahead of the horizon: its slope change is
        added to that end's. An event at its pixel's last knot time adds to that knot's ramp.

        ``slopes``: ``round(2**K / length)`` for each ramp length up to ``D`` (a table: no
        division an event). ``pixels``: ``(W * H, 4)``, each pixel's last knot time, the one
        before, and their ends' places in the ring (-1: none). ``e_active``, ``s_active``: the
        change of the region's count of active ramps (for the doubt's bound).

        Returns the rings' new tails ``(ends, starts)``.
        """
        one = np.int64(1) << K
        for i in range(xs.shape[0]):
            x, y, t = np.int64(xs[i]), np.int64(ys[i]), ts[i]
            c = 1 if ps[i] else -1
            pixel = y * width + x
            r = row[y] * out_w + column[x]
            if t > pixels[pixel, 0] or pixels[pixel, 2] < 0:  # a new knot: a new end
                pixels[pixel, 1], pixels[pixel, 3] = pixels[pixel, 0], pixels[pixel, 2]
                pixels[pixel, 0], pixels[pixel, 2] = t, ends
                e_t[ends & mask], e_region[ends & mask] = t, r
                e_slope[ends & mask], e_jump[ends & mask], e_active[ends & mask] = 0, 0, 0
                ends += 1
            t0 = pixels[pixel, 1]
            h = max(t0, t - delay)
            length = t - h  # 0 for a first event at t_start: a jump, no ramp
            slope = c * slopes[length]  # round(2**K / length), 0 for a jump
            end = pixels[pixel, 2] & mask
            e_slope[end] -= slope
            e_jump[end] += c * one - slope * length
            if length:
                e_active[end] -= 1
            if t0 > t - delay and pixels[pixel, 3] >= 0:
                e_slope[pixels[pixel, 3] & mask] += slope
                e_active[pixels[pixel, 3] & mask] += 1
            elif slope != 0:
                s_t[starts & mask], s_region[starts & mask] = max(t - delay, t_start), r
                s_slope[starts & mask], s_active[starts & mask] = slope, 1
                starts += 1
        return ends, starts

    @numba.njit(nogil=True)
    def sweep(head_e, tail_e, e_t, e_region, e_slope, e_jump, e_active, head_s, tail_s, s_t,
              s_region, s_slope, s_active, mask, horizon, value, slope_sum, since, pending, q,
              active, delay, level, b, out_r, out_t, out_on, doubt_r, doubt_t,
              n_doubt):  # pragma: no cover - compiled
        """The slope changes before the horizon, in time order (a merge of the two rings).

        Each region is advanced lazily: to a change's time when one comes (its pending jump
        at its own time, then its ramp), and to the horizon at the end. One loop body, no
        call inside: a compiled call taking arrays counts their references each time, which
        made this loop ten times slower.

        *Doubts*: with ``A`` ramps active in a region, its integer value is within ``E = A * D
        / 2`` units of the exact one and its slope within ``A / 2`` units a microsecond. A
        value within ``E`` of a level, and a crossing whose time lies within
        ``E / (|slope| - A / 2)`` of a half tick, could go the other way in exact arithmetic:
        they are recorded (region and time), where an exact rule would decide them.

        Returns the rings' new heads, the outputs' count and the doubts' count.
        """
        n_out = 0
        regions = value.shape[0]
        final = 0  # after the rings: each region in turn, to the horizon
        next_end = e_t[head_e & mask] if head_e < tail_e else horizon
        next_start = s_t[head_s & mask] if head_s < tail_s else horizon
        while final < regions:
            if next_end < horizon or next_start < horizon:
                if next_end <= next_start:
                    k = head_e & mask
                    t, r, d_slope, d_jump = next_end, e_region[k], e_slope[k], e_jump[k]
                    d_active = e_active[k]
                    head_e += 1
                    next_end = e_t[head_e & mask] if head_e < tail_e else horizon
                else:
                    k = head_s & mask
                    t, r, d_slope, d_jump = next_start, s_region[k], s_slope[k], 0
                    d_active = s_active[k]
                    head_s += 1
                    next_start = s_t[head_s & mask] if head_s < tail_s else horizon
            else:
                t, r, d_slope, d_jump, d_active = horizon, final, 0, 0, 0
                final += 1
            t_now = since[r]
            if t > t_now:
                v, qr, sl, jump = value[r], q[r], slope_sum[r], pending[r]
                bound = b * (active[r] * delay // 2 + 1)  # b * E, with a unit to spare
                for piece in range(2):  # the jump at t_now, then the ramp to t
                    if piece == 0:
                        if jump == 0:
                            continue
                        v1 = v + jump
                    else:
                        if sl == 0:
                            break
                        v1 = v + sl * (t - t_now)
                    scaled = b * v1
                    d = 1 if scaled >= (qr + 1) * level else -1 if scaled <= (qr - 1) * level else 0
                    while d != 0 and d * scaled >= d * (qr + d) * level:
                        qr += d
                        out_t[n_out] = t_now
                        if piece == 1:  # the rounded crossing time, floor(t + 1/2)
                            num, den = qr * level - b * v, b * sl
                            out_t[n_out] += (2 * num + den) // (2 * den)
                        out_r[n_out], out_on[n_out] = r, d > 0
                        n_out += 1
                        if piece == 1 and active[r] > 0:
                            spare = abs(sl) - active[r] / 2
                            half = abs((num / den) % 1.0 - 0.5)
                            if spare <= 0 or half <= (bound / b) / spare:
                                doubt_r[n_doubt], doubt_t[n_doubt] = r, out_t[n_out - 1]
                                n_doubt += 1
                    near = scaled % level
                    if active[r] > 0 and min(near, level - near) <= bound:
                        doubt_r[n_doubt], doubt_t[n_doubt] = r, t if piece == 1 else t_now
                        n_doubt += 1
                    v = v1
                value[r], since[r], q[r], pending[r] = v, t, qr, 0
            slope_sum[r] += d_slope
            pending[r] += d_jump
            active[r] += d_active
        return head_e, head_s, n_out, n_doubt

    return {"ramps": ramps, "sweep": sweep}


class StreamingLinear:
    """The design as a session: ``__call__(chunk)`` returns the decided events, sorted."""

    def __init__(self, loops: dict, t_start: int, max_events: int) -> None:
        self.loops = loops
        width, height, _ = SENSOR
        self.out_w, out_h = width // FACTOR, height // FACTOR
        regions = self.out_w * out_h
        self.column = np.arange(width, dtype=np.int64) // FACTOR
        self.row = np.arange(height, dtype=np.int64) // FACTOR
        self.t_start = t_start
        length = np.arange(REALTIME_MAX_DELAY_US + 1, dtype=np.int64)
        self.slopes = ((1 << K) + length // 2) // np.maximum(length, 1)
        self.slopes[0] = 0
        self.pixels = np.full((width * height, 4), t_start, np.int64)
        self.pixels[:, 2:] = -1
        size = 1 << int(4 * max_events).bit_length()  # a chunk's changes and those ahead
        self.mask = size - 1
        self.ends = [np.zeros(size, np.int64) for _ in range(5)]
        self.starts = [np.zeros(size, np.int64) for _ in range(4)]
        self.head_e = self.tail_e = self.head_s = self.tail_s = 0
        self.regions = [np.zeros(regions, np.int64), np.zeros(regions, np.int64),
                        np.full(regions, t_start, np.int64), np.zeros(regions, np.int64),
                        np.zeros(regions, np.int64), np.zeros(regions, np.int64)]
        # value, slope, since, pending jump, q, active ramps
        self.out = (np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size, np.bool_))
        self.doubt = (np.empty(size, np.int64), np.empty(size, np.int64))
        self.doubts: list[tuple[np.ndarray, np.ndarray]] = []  # (region, time) of each chunk
        self.horizon = t_start
        a, b = THRESHOLD
        self.b, self.level = b, a * FACTOR * FACTOR * (1 << K)

    def __call__(self, chunk: np.ndarray) -> np.ndarray:
        t = chunk["t"]
        self.tail_e, self.tail_s = self.loops["ramps"](
            chunk["x"], chunk["y"], t, chunk["p"], SENSOR[0], self.column, self.row, self.out_w,
            REALTIME_MAX_DELAY_US, self.slopes, self.t_start, self.pixels, self.tail_e, *self.ends,
            self.tail_s, *self.starts, self.mask)
        self.horizon = max(self.horizon, int(t[-1]) - REALTIME_MAX_DELAY_US)
        self.head_e, self.head_s, n_out, n_doubt = self.loops["sweep"](
            self.head_e, self.tail_e, *self.ends, self.head_s, self.tail_s, *self.starts,
            self.mask, self.horizon, *self.regions, REALTIME_MAX_DELAY_US, self.level, self.b,
            *self.out, *self.doubt, 0)
        self.doubts.append((self.doubt[0][:n_doubt].copy(), self.doubt[1][:n_doubt].copy()))
        out_r, out_t, out_on = (column[:n_out] for column in self.out)
        order = np.argsort(out_t, kind="stable")
        result = np.empty(n_out, chunk.dtype)
        result["x"], result["y"] = out_r[order] % self.out_w, out_r[order] // self.out_w
        result["t"], result["p"] = out_t[order], out_on[order]
        return result


def design_whole(events: np.ndarray, before: int) -> np.ndarray:
    """The design's events earlier than ``before``, the whole stream at once: its eager twin.

    Vectorised torch, no loop over events or regions: each event's ramp (its pixel's previous
    knot from a stable sort by pixel), the slope changes and jumps summed per region and time
    (one sort), the region's slope and value at each breakpoint as integer cumulative sums,
    then the package's reference rule over the moves (each breakpoint's ramp, then its jump,
    :func:`~evdown_torch.transforms.functional.reference.move_crossings`) and the loop's
    rounded crossing times. Integers throughout, so it must give the loop's session's events,
    whatever the chunks.

    Args:
        events: a time-sorted Tonic structured array (``t`` integer microseconds).
        before: the cut (the session's last horizon).

    Returns:
        The events earlier than ``before``, sorted by ``t`` (stable), of the input's dtype.
    """
    width = SENSOR[0]
    out_w = width // FACTOR
    a, b = THRESHOLD
    level = a * FACTOR * FACTOR * (1 << K)
    one, delay = 1 << K, REALTIME_MAX_DELAY_US
    x = torch.from_numpy(events["x"].astype(np.int64))
    y = torch.from_numpy(events["y"].astype(np.int64))
    t = torch.from_numpy(events["t"].astype(np.int64))
    c = torch.from_numpy(np.where(events["p"], 1, -1).astype(np.int64))
    t_start = int(t[0])
    pixel, order = torch.sort(y * width + x, stable=True)  # time order inside a pixel
    t, c, x, y = t[order], c[order], x[order], y[order]
    first_of_pixel = changes(pixel)
    new_knot = first_of_pixel | changes(t)
    previous = torch.where(first_of_pixel, t_start, torch.roll(t, 1))  # read at new knots
    t0 = take(take(previous, where_true(new_knot)), run_index(new_knot))
    h = torch.maximum(t0, t - delay)
    length = t - h
    slope = c * torch.where(length > 0, (one + length // 2) // length.clamp(min=1), 0)
    region = (y // FACTOR) * out_w + x // FACTOR
    ramp = where_true(length > 0)
    at = torch.cat([take(h, ramp), t])
    where = torch.cat([take(region, ramp), region])
    d_slope = torch.cat([take(slope, ramp), -slope])
    d_jump = torch.cat([torch.zeros_like(ramp), c * one - slope * length])
    # Per (region, time): one breakpoint, its slope change and jump.
    span = int(t.max()) - t_start + 1
    key, by_key = torch.sort(where * span + (at - t_start), stable=True)
    new_point = changes(key)
    point = run_index(new_point)
    n_points = int(point[-1]) + 1
    slope_change = torch.zeros(n_points, dtype=torch.int64).index_add_(0, point, d_slope[by_key])
    jump = torch.zeros(n_points, dtype=torch.int64).index_add_(0, point, d_jump[by_key])
    first_point = where_true(new_point)
    point_t = t_start + take(key, first_point) % span
    point_region = take(key, first_point) // span
    first = changes(point_region)
    starts, run = where_true(first), run_index(first)
    slope_after = segmented_cumsum(slope_change, starts, run)
    slope_before = torch.where(first, 0, torch.roll(slope_after, 1))
    gap = torch.where(first, 0, point_t - torch.roll(point_t, 1))
    value = segmented_cumsum(slope_before * gap + jump, starts, run)  # after the jumps
    value_before_jump = value - jump
    start_value = torch.where(first, 0, torch.roll(value, 1))  # the ramp's start
    # Moves: each point's ramp, then its jump.
    move_value = torch.stack([value_before_jump, value], 1).reshape(-1)
    move_first = torch.stack([first, torch.zeros_like(first)], 1).reshape(-1)
    scaled = b * move_value
    floor_u = torch.div(scaled, level, rounding_mode="floor")
    cross = move_crossings(floor_u, scaled - floor_u * level == 0, move_first)
    k, is_jump = cross.move // 2, cross.move % 2 == 1
    sl = take(slope_before, k)
    num = cross.level * level - b * take(start_value, k)
    den = b * sl
    on_ramp = torch.div(2 * num + den, torch.where(is_jump, 1, 2 * den), rounding_mode="floor")
    t_prev = take(torch.where(first, point_t, torch.roll(point_t, 1)), k)
    out_t = torch.where(is_jump, take(point_t, k), t_prev + on_ramp)
    out_region = take(point_region, k)
    keep = where_true(out_t < before)
    out_t, out_region, on = take(out_t, keep), take(out_region, keep), take(cross.on, keep)
    out_t, order = torch.sort(out_t, stable=True)
    result = np.empty(out_t.shape[0], events.dtype)
    region_sorted = take(out_region, order).numpy()
    result["x"], result["y"] = region_sorted % out_w, region_sorted // out_w
    result["t"], result["p"] = out_t.numpy(), take(on, order).numpy()
    return result


def main(argv: list[str] | None = None) -> int:
    replay = estimate_replay(argv, __doc__, compiled=numba is not None, sensor_size=SENSOR)
    if replay is None:
        return 2
    stream, bounds, last = replay
    chunks = [stream[int(bounds[k]):int(bounds[k + 1])] for k in range(last + 1)]
    a, b = THRESHOLD
    sessions = {
        "floor": RegionFloor(SENSOR, FACTOR).session(),
        "package": make_method("linear", SENSOR, FACTOR, threshold=a / b,
                               max_delay=REALTIME_MAX_DELAY_US).session(),
        "design": StreamingLinear(compile_loops(), int(stream["t"][0]),
                                  max(len(c) for c in chunks)),
    }
    seconds: dict[str, list[float]] = {name: [] for name in sessions}
    outputs: dict[str, list[np.ndarray]] = {name: [] for name in sessions}
    for k, chunk in enumerate(chunks):  # chunk 0 warms up (and compiles)
        for name, session in sessions.items():
            start = time.perf_counter()
            made = session(chunk)
            if k:
                seconds[name].append(time.perf_counter() - start)
            outputs[name].append(made)
    n_events = int(bounds[last + 1] - bounds[1])
    floor_total = sum(seconds["floor"])
    floor_p99 = float(np.quantile(seconds["floor"], 0.99))
    print(f"{last} chunks of 10 ms, {n_events:,} events (25 M/s on average), "
          f"max_delay {REALTIME_MAX_DELAY_US} us, threshold {a / b}; wall time, one thread\n")
    print("| session | median chunk (ms) | p99 chunk (ms) | ns per event | x floor (p99s, as "
          "the replay) | x floor (total times) | output events |")
    print("|---|---|---|---|---|---|---|")
    for name, times in seconds.items():
        p99 = float(np.quantile(times, 0.99))
        made = sum(len(o) for o in outputs[name])
        print(f"| {name} | {1e3 * statistics.median(times):.2f} | {1e3 * p99:.2f} "
              f"| {1e9 * sum(times) / n_events:.1f} | {floor_p99 / p99:.4f} "
              f"| {floor_total / sum(times):.4f} | {made:,} |")
    horizon = min(int(np.concatenate(outputs[n])["t"].max()) for n in ("package", "design"))

    def keys(name: str, before: int) -> Counter:
        out = np.concatenate(outputs[name])
        out = out[out["t"] < before]
        return Counter(zip(out["x"].tolist(), out["y"].tolist(), out["t"].tolist(),
                           out["p"].tolist(), strict=True))

    # Events before the cut; their partners a tick away may lie on it.
    package, design = keys("package", horizon - 1), keys("design", horizon - 1)
    only_package, only_design = package - design, design - package
    spare = keys("design", horizon) - keys("package", horizon)
    paired = 0
    for (x, y, t, p), count in only_package.items():
        for shifted in ((x, y, t - 1, p), (x, y, t + 1, p)):
            matched = min(count, spare[shifted])
            spare[shifted] -= matched
            count -= matched
            paired += matched
    print(f"\nbefore t = {horizon - 1}: package {sum(package.values()):,} events, design "
          f"{sum(design.values()):,}; in one and not the other: "
          f"{sum(only_package.values()):,} and {sum(only_design.values()):,}, of which "
          f"{paired:,} pairs one tick apart")
    doubt_region = np.concatenate([r for r, _ in sessions["design"].doubts])
    doubt_t = np.concatenate([t for _, t in sessions["design"].doubts])
    by_region = {int(r): np.sort(doubt_t[doubt_region == r]) for r in np.unique(doubt_region)}
    out_w = SENSOR[0] // FACTOR
    # A differing event is within a doubt's reach when its region had a doubt in the 2 ms up
    # to it (a touch moves q, hence the region's next crossings) or a tick after it.
    reached = 0
    for (x, y, t, _), count in (only_package + only_design).items():
        times = by_region.get(y * out_w + x, np.zeros(0, np.int64))
        at = np.searchsorted(times, t + 2, side="right")
        reached += count * int(at > 0 and times[at - 1] >= t - 2000)
    print(f"doubts (the design's integers within their error bound of a level or of a half "
          f"tick): {len(doubt_t):,}, {1e6 * len(doubt_t) / n_events:.1f} per million input "
          f"events; differing events within a doubt's reach: {reached:,} of "
          f"{sum(only_package.values()) + sum(only_design.values()):,}")
    # The eager twin on everything the session read, at once, against the session's chunks.
    cut = sessions["design"].horizon
    start = time.perf_counter()
    whole = design_whole(stream[: int(bounds[last + 1])], cut)
    seconds_whole = time.perf_counter() - start
    chunked = np.concatenate(outputs["design"])
    chunked = np.sort(chunked[chunked["t"] < cut], order=["t", "x", "y", "p"])
    same = np.array_equal(chunked, np.sort(whole, order=["t", "x", "y", "p"]))
    print(f"eager twin, the {int(bounds[last + 1]):,} events at once (torch, one thread): "
          f"{len(whole):,} events before t = {cut}, {'the same as' if same else 'NOT the same as'}"
          f" the session's in {last + 1} chunks; {seconds_whole:.1f} s "
          f"({1e9 * seconds_whole / int(bounds[last + 1]):.0f} ns per input event)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
