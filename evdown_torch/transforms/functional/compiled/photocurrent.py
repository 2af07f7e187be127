"""PhotocurrentPooling's compiled events-mode loop: each event's region photocurrent, in turn.

The reference rule runs on each event's ``u`` in time order, as in the eager kernel.

Each touched region keeps, during a call, an integer sum ``S`` of its pixels' intensities in
fixed point against an anchor level ``a`` (the region's brightest pixel when it is anchored):
``S = sum round(exp(c * (L_p - a)) * 2**bits)``. An event changes ``S`` by its pixel's new
intensity minus its old one, exactly (integers), so a region's sum after any number of events
is its pixels' current intensities, each rounded once. The region is anchored again (its sum
recomputed from its pixels) when a pixel's intensity climbs more than :data:`HEADROOM_BITS`
bits above the anchor's or when the sum falls below ``2**(bits - DROP_BITS)`` (every pixel fell
well below it), so the sum always holds its pixels to ``n_r / 2**(bits - 3)`` of their total
or better (``3e-14`` at ``n_r = 16``). Then ``u = (c * a
- log(n_r) + log(S / 2**bits)) / theta`` goes through the snap of
:func:`~..photocurrent.levels.snap` and the reference rule.

Most events keep their region's reference index ``q``: the rule moves it only once ``u``
reaches ``q + 1 - SNAP`` or ``q - 1 + SNAP``. So each region also keeps the two sums at
those bounds, brought inside them by more than both paths' error bounds
(:func:`_stay_bounds`, an ``exp`` each time the region's anchor or ``q`` changes), and an
event whose sum stays strictly between them is done with two integer comparisons: no
logarithm, no doubt test. Any other event takes ``u`` as above.

The eager kernel (:mod:`..photocurrent.events_mode`) sums in other ways (its two-word sums
hold each sum to ``1e-10 * theta``, :func:`~..photocurrent.sums.two_word_scale`), so the two
``u`` differ by a few of those units; they decide every event alike unless its ``u`` lies
within their two error bounds of a snap bound (``k - SNAP`` or ``k + SNAP``). The loop checks
every event that takes ``u`` against both bounds (as
:func:`~..photocurrent.one_word.one_word_moves` checks its own; an event kept between the stay
bounds needs none, both paths' ``u`` lying strictly between the snap bounds that would move
``q``): an event in doubt, after anchoring its region afresh, hands the whole call to the
eager kernel, as does an output past :func:`~evdown_torch.checks.output_limit` (whose error
the eager kernel raises). So both paths give the same events and the same state, bit for bit.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from evdown_torch._regions import region_pixel_count
from evdown_torch.checks import output_limit
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop, inlined_helper
from evdown_torch.transforms.functional.compiled.regions import (
    columns_of,
    crossing_columns,
    crossing_tensors,
    grown_columns,
    outside_error,
    region_tables,
)
from evdown_torch.transforms.functional.photocurrent.settings import PhotocurrentState
from evdown_torch.transforms.functional.photocurrent.sums import EPS
from evdown_torch.transforms.functional.reference import SNAP

__all__ = ["DROP_BITS", "HEADROOM_BITS", "TABLE_LEVELS", "photocurrent_step"]

#: Bits above a region's anchor its pixels may climb before the region is anchored again.
HEADROOM_BITS = 4

#: Bits a region's sum may fall below one anchored pixel's before it is anchored again.
DROP_BITS = 4

#: Most levels of the table of intensities (below: ``exp`` per event).
TABLE_LEVELS = 1 << 16

#: The eager kernel's error bound on a region's sum, relative to it, is this times ``theta``
#: (at least ``24 * EPS``): :func:`~..photocurrent.sums.two_word_scale`'s tolerance.
EAGER_TOLERANCE = 1e-10

_DONE, _GROW, _DOUBT, _OUTSIDE = 0, 1, 2, 3
_LOWEST = -(2**63)  # below every level


@inlined_helper  # (read twice an event by the loop)
def _intensity(j: int, table: np.ndarray, lo: int, contrast: float,
               scale: float) -> int:  # pragma: no cover - compiled
    """``round(exp(c * j) * scale)``, 0 at ``j < lo``; from ``table`` where it reaches.

    The same value for the same ``j`` throughout a call (table or not), so a region's sum
    telescopes exactly.
    """
    if j < lo:
        return 0
    if table.shape[0] > 0:
        return table[np.uint64(j - lo)]  # (j >= lo: unsigned, ``_numba``)
    return int(math.floor(math.exp(contrast * j) * scale + 0.5))


@compiled_loop
def _anchor_region(
    r: int, level: np.ndarray, width: int, out_w: int, fx: int, fy: int, rows: int,
    period: int, height: int, table: np.ndarray, lo: int, contrast: float, scale: float,
    anchor: np.ndarray, total: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Anchor region ``r`` at its brightest pixel and sum its pixels' intensities."""
    rx = r % out_w
    ry = r // out_w
    x0 = rx * fx
    x1 = min(x0 + fx, width)
    y0 = ry * fy
    y1 = min(y0 + fy, rows)
    brightest = _LOWEST
    for py in range(y0, y1):
        if py % period < height:
            for px in range(x0, x1):
                brightest = max(brightest, level[py * width + px])
    s = 0
    for py in range(y0, y1):
        if py % period < height:
            for px in range(x0, x1):
                s += _intensity(level[py * width + px] - brightest, table, lo, contrast, scale)
    anchor[r] = brightest
    total[r] = s


@compiled_loop
def _u_and_doubt(
    a: int, s: int, log_n: float, n_r: int, contrast: float, threshold: float, scale: float,
) -> tuple[float, bool]:  # pragma: no cover - compiled
    """``u`` of a region anchored at ``a`` with sum ``s``, and whether it is in doubt.

    In doubt: within the loop's error bound plus the eager kernel's of a snap bound.
    ``scale``: the fixed point's ``2.0**bits`` (dividing by it is exact, and costs no
    ``pow``).
    """
    log_v = math.log(s / scale)  # in [2**-DROP_BITS, n_r * 2**HEADROOM_BITS]
    ca = contrast * a
    u = (ca - log_n + log_v) / threshold
    # The loop's sum: half a unit per pixel, and a few ulps of each exp(c * j) (|c j| < 64).
    spare = s - 0.5 * n_r
    if spare <= 0:
        return u, True
    relative = 0.5 * n_r / spare + 128 * EPS
    # The eager sums' tolerance, and a few ulps of every term of both u (the eager anchor may
    # lie MAX_EXPONENT from this one, its sum's logarithm up to 64 log 2).
    eager = max(EAGER_TOLERANCE * threshold, 24 * EPS)
    terms = abs(ca) + abs(log_v) + log_n + 80.0
    margin = 2 * (1.01 * (relative + eager) + 8 * EPS * terms) / threshold + 8 * EPS * abs(u)
    nearest = math.floor(u + 0.5)
    return u, abs(abs(u - nearest) - SNAP) <= margin


@compiled_loop
def _stay_bounds(
    r: int, anchor: np.ndarray, reference: np.ndarray, log_pixels: np.ndarray,
    contrast: float, threshold: float, scale: float, slack: float, low: np.ndarray,
    high: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The sums ``low[r] < S < high[r]`` of region ``r`` that keep its ``q``, beyond doubt.

    ``q`` stays while ``q - 1 + SNAP < u < q + 1 - SNAP``; at such sums, taken ``slack``
    (log units) inside those bounds, the exact ``u`` lies inside them by more than both
    paths' error bounds, so both paths keep ``q`` and emit nothing. ``scale``: the fixed
    point's ``2.0**bits`` (a product by it is exact: no ``ldexp`` call).
    """
    q = reference[r]
    ca = contrast * anchor[r]
    log_n = log_pixels[r]
    # A few ulps of every term of both paths' u and of these exponents (more than
    # _u_and_doubt's margin allows for them).
    terms = threshold * (abs(q) + 2.0) + abs(ca) + 2 * log_n + 100.0
    spare = slack + 64 * EPS * terms
    # u(S) = (c a - log(n_r) + log(S / 2**bits)) / theta: log(S / 2**bits) at q +- (1 - SNAP).
    top = threshold * (q + 1 - SNAP) - ca + log_n - spare
    bottom = threshold * (q - 1 + SNAP) - ca + log_n + spare
    ceiling = 2.0**62  # above every sum
    high[r] = int(min(math.floor(math.exp(min(top, 64.0)) * scale), ceiling))
    low[r] = int(min(math.ceil(math.exp(min(bottom, 64.0)) * scale), ceiling))


@compiled_loop
def _photocurrent_loop(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, column: np.ndarray, row: np.ndarray,
    width: int, rows: int, period: int, height: int, out_w: int, fx: int, fy: int,
    pixels: np.ndarray, log_pixels: np.ndarray, level: np.ndarray, reference: np.ndarray,
    anchor: np.ndarray, total: np.ndarray, ready: np.ndarray, low: np.ndarray,
    high: np.ndarray, table: np.ndarray, lo: int, highest: int, contrast: float,
    threshold: float, bits: int, scale: float, slack: float, start: int, resume: bool, k: int,
    room: int, out_x: np.ndarray, out_y: np.ndarray, out_source: np.ndarray,
    out_on: np.ndarray,
) -> tuple[int, int, int, int]:  # pragma: no cover - compiled
    """The reference rule after each time-sorted event ``start, start + 1, ...``.

    Writes each crossing's region ``(rx, ry)``, source event and polarity at ``k, k + 1, ...``.
    An event whose region's sum stays between ``low`` and ``high`` (:func:`_stay_bounds`)
    keeps the region's ``q``: no logarithm, no doubt test.
    ``resume``: event ``start`` has already moved its pixel and region sum (a call that
    stopped there for room). ``room``: most crossings in all (-1: no limit).

    Returns:
        ``(status, event, crossings so far, crossings needed)``: ``_DONE`` after the last
        event; ``_GROW`` at an event whose crossings do not fit the outputs (its pixel and sum
        moved, its rule not applied); ``_DOUBT`` at an event in doubt or past ``room``;
        ``_OUTSIDE`` at an event whose pixel lies outside the sensor (nothing of it applied).
    """
    n = x.shape[0]
    capacity = out_source.shape[0]
    low_mark = 1 << (bits - DROP_BITS)
    padded = period > height  # stacked recordings with rows between them
    for i in range(start, n):
        xi = x[i]
        yi = y[i]
        if xi < 0 or xi >= width or yi < 0 or yi >= rows or (padded and yi % period >= height):
            return _OUTSIDE, i, k, 0
        rx = column[np.uint64(xi)]  # (unsigned indices: ``_numba``, "Unsigned indices")
        ry = row[np.uint64(yi)]
        r = ry * out_w + rx
        ru = np.uint64(r)
        if not (resume and i == start):
            pixel = np.uint64(yi * width + xi)
            before = level[pixel]
            after = before + (1 if p[i] else -1)
            level[pixel] = after
            a = anchor[ru]
            again = not ready[ru] or after - a > highest
            if not again:
                s = total[ru] + (_intensity(after - a, table, lo, contrast, scale)
                                 - _intensity(before - a, table, lo, contrast, scale))
                total[ru] = s
                again = s < low_mark
            if again:  # first touched, climbing past the headroom, or fallen below it
                _anchor_region(r, level, width, out_w, fx, fy, rows, period, height, table,
                               lo, contrast, scale, anchor, total)
                ready[r] = True
                _stay_bounds(r, anchor, reference, log_pixels, contrast, threshold, scale,
                             slack, low, high)
            if low[ru] < total[ru] < high[ru]:
                continue  # q stays: no u needed
        u, doubt = _u_and_doubt(anchor[r], total[r], log_pixels[r], pixels[r], contrast,
                                threshold, scale)
        if doubt:  # anchored afresh, the sum holds the most bits it can
            _anchor_region(r, level, width, out_w, fx, fy, rows, period, height, table, lo,
                           contrast, scale, anchor, total)
            u, doubt = _u_and_doubt(anchor[r], total[r], log_pixels[r], pixels[r], contrast,
                                    threshold, scale)
            _stay_bounds(r, anchor, reference, log_pixels, contrast, threshold, scale, slack,
                         low, high)
            if doubt:
                return _DOUBT, i, k, 0
        # The snap: floor(u), and whether u is on a level.
        nearest = math.floor(u + 0.5)
        offset = u - nearest
        on_level = abs(offset) <= SNAP
        floor_u = nearest - 1 if offset < -SNAP else nearest
        q = reference[r]
        # The reference rule: onto the level u is on, else into the cell around u.
        q_new = floor_u if on_level else min(max(q, floor_u), floor_u + 1)
        count = abs(q_new - q)
        if count == 0:
            continue
        if room >= 0 and k + count > room:
            return _DOUBT, i, k, 0
        if k + count > capacity:
            return _GROW, i, k, k + count
        d = 1 if q_new > q else -1
        for _ in range(count):
            out_x[k] = rx
            out_y[k] = ry
            out_source[k] = i
            out_on[k] = d > 0
            k += 1
        reference[r] = q_new
        _stay_bounds(r, anchor, reference, log_pixels, contrast, threshold, scale, slack, low,
                     high)
    return _DONE, n, k, 0


@functools.lru_cache(maxsize=32)
def _region_sizes(
    sensor_size: tuple[int, int, int], factor: tuple[int, int], regions: int
) -> tuple[np.ndarray, np.ndarray]:
    """``n_r`` (int64) and ``log(n_r)`` (float64) of each of ``regions`` regions.

    Shared between calls, never written.
    """
    pixels = region_pixel_count(torch.arange(regions), sensor_size, factor)
    return pixels.numpy(), pixels.to(torch.float64).log_().numpy()


@functools.lru_cache(maxsize=32)
def _intensities(contrast: float, per_region: int) -> tuple[np.ndarray, int, int, int, float]:
    """``(table, lo, highest, bits, scale)`` of a call's fixed point.

    A region's sum stays below ``2**62``: each of its ``per_region`` pixels at most
    ``2**(bits + HEADROOM_BITS)`` (``highest`` levels above the anchor at most). Levels below
    ``lo`` round to 0. The table holds ``lo .. highest`` when they are few
    (:data:`TABLE_LEVELS`), else it is empty and each intensity takes an ``exp``.
    """
    bits = 62 - HEADROOM_BITS - per_region.bit_length()
    scale = math.ldexp(1.0, bits)
    highest = max(math.floor(HEADROOM_BITS * math.log(2) / contrast), 0)
    highest = min(highest, 1 << 20)
    # exp(c * j) * 2**bits < 1/2 below lo: it rounds to 0.
    lo = math.floor(-(bits + 2) * math.log(2) / contrast)
    if highest - lo + 1 > TABLE_LEVELS:
        return np.empty(0, np.int64), lo, highest, bits, scale
    j = np.arange(lo, highest + 1, dtype=np.float64)
    table = np.floor(np.exp(contrast * j) * scale + 0.5).astype(np.int64)
    return table, lo, highest, bits, scale


def _stay_slack(per_region: int, bits: int, threshold: float) -> float:
    """Log units between a sum that keeps ``q`` (:func:`_stay_bounds`) and a bound's.

    Twice both paths' error bounds on a region's sum, relative to it (as
    :func:`_u_and_doubt`'s margin): the loop's at its smallest sum (``2**(bits - DROP_BITS)``,
    below which a region is anchored again) and the eager kernel's. Infinite where the
    smallest sum cannot hold the loop's rounding: no sum keeps ``q`` untested.
    """
    smallest = 1 << (bits - DROP_BITS)
    if smallest <= 2 * per_region:
        return math.inf
    loop = 0.5 * per_region / (smallest - per_region) + 128 * EPS
    eager = max(EAGER_TOLERANCE * threshold, 24 * EPS)
    return 2 * 1.01 * (loop + eager)


def photocurrent_step(
    events: Events, sensor_size: tuple[int, int, int], factor: tuple[int, int],
    contrast: float, threshold: float, state: PhotocurrentState,
) -> tuple[Events, PhotocurrentState] | None:
    """``photocurrent_sorted`` of ``N >= 1`` time-sorted events on the CPU.

    The same events and state as :func:`~..photocurrent.events_mode.photocurrent_sorted`
    (new tensors; ``state`` is not written).

    ``None`` where the eager kernel must decide the call: an event whose ``u`` lies too near a
    snap bound for the two paths' error bounds, or an output past the limit in force (the
    eager kernel raises its error).

    Raises:
        ValueError: for an event whose pixel lies outside the sensor.
    """
    width, height, _ = sensor_size
    fx, fy = factor
    regions = state.reference.shape[0]
    rows = state.level.shape[0] // width
    out_w = -(-width // fx)
    out_h = -(-height // fy)
    period = out_h * fy if regions > out_w * out_h else rows  # stacked recordings' rows
    column, row = region_tables(factor, out_w, regions // out_w)
    pixels, log_pixels = _region_sizes(sensor_size, factor, regions)
    table, lo, highest, bits, scale = _intensities(float(contrast), fx * fy)
    n = events.num_events
    level, reference = state.level.clone(), state.reference.clone()
    levels, references = level.numpy(), reference.numpy()
    anchor = np.empty(regions, np.int64)
    total = np.empty(regions, np.int64)
    ready = np.zeros(regions, np.bool_)
    low, high = np.empty(regions, np.int64), np.empty(regions, np.int64)
    slack = _stay_slack(fx * fy, bits, threshold)
    x, y, p = columns_of(events.x, events.y, events.p)
    limit = output_limit()
    room = -1 if limit is None else limit
    capacity = 2 * n + 16 if limit is None else min(2 * n + 16, limit + 1)
    out = crossing_columns(capacity)
    i, k, resume = 0, 0, False
    while True:
        status, i, k, needed = _photocurrent_loop(
            x, y, p, column, row, width, rows, period, height, out_w, fx, fy, pixels,
            log_pixels, levels, references, anchor, total, ready, low, high, table, lo,
            highest, float(contrast), float(threshold), bits, scale, slack, i, resume, k, room,
            *out)
        if status == _DONE:
            break
        if status == _OUTSIDE:
            raise outside_error(i, x, y, np.empty(width, np.int8), np.empty(rows, np.int8))
        if status == _DOUBT:
            return None
        capacity = max(2 * capacity, needed) if limit is None else max(
            min(2 * capacity, limit), needed)
        out, resume = grown_columns(out, k, capacity), True
    out_x, out_y, source, on = crossing_tensors(out, k)
    output = Events(out_x, out_y, events.t.index_select(0, source), on)
    return output, PhotocurrentState(level, reference, events.t[-1].clone())
