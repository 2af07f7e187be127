"""DensitySubsampling compiled: a step's decisions in one loop, and the eager kernel's lookups.

:func:`~evdown_torch.transforms.functional.density._density_sorted` needs, for each event and
each offset of its patch, the neighbour pixel's last event up to this one in stream order; the
eager kernel finds it by a binary search over the events grouped by pixel (half of its time
on the live replay's chunks). This loop walks the events in stream order keeping each pixel's
latest event (its place among the grouped events) in a table, and reads the neighbours'
there: the same event wherever one exists (where none does, the eager search's answer is not
the neighbour's either, and both paths discard it), so the densities are the same, bit for
bit. The eager kernel takes it where it runs on the CPU.

A session's step on the CPU (:func:`decide_in_order`) goes further: one loop over the events
in stream order decides each one, with no ``exp`` per neighbour. Each pixel and polarity keeps
its decayed count *scaled* to a clock origin ``o``: ``A_j = S_j * exp((t_j - o) / tau)``
(``S_j`` its count after its last event, at ``t_j``; scaled from the state when the call
starts, for the pixels of its events' patches only where those cover less than the sensor: a
call on a large sensor scales no more than it reads, though it still copies the state's two
columns). An event at ``t`` adds
``exp((t - o) / tau)`` to its pixel's ``A``, and its density is
``sum_j w_j A_j / exp((t - o) / tau)``: one ``exp`` an event. The Gaussian is separable
(``w = g(dx) g(dy)``), so the loop keeps each position's row sum ``sum_dx g(dx) A``, adds an
event's ``g(dx) exp((t - o) / tau)`` to the ``k`` row sums around it and reads the ``k`` of
its column: ``2 k`` terms an event, not ``k * k``. The origin moves to the event's
time whenever ``(t - o) / tau`` would pass :data:`SPAN_LIMIT` (every ``A`` then shrinks by
``exp(-(t - o) / tau)``), so nothing overflows. This rounds otherwise than the eager kernel's
doubling scan and per-neighbour decays: the loop bounds both roundings, relative to the exact
density of the call's events from the state given (:func:`_doubt_bound`), and an event whose
draw lies within that bound of ``s * density`` (its decision could differ between the paths)
hands the whole call to the eager kernel. So both paths keep the same events of every call
given the same state. The new state's counts are the loop's (each within its bound of the
exact ones), so two sessions run wholly on different paths hold states a few ``1e-13``
apart, and can decide differently only for an event whose draw lies that close to
``s * density`` (docs/semantics.md, "How the subsamplers are computed").
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from evdown_torch.checks import output_size
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop, inlined_helper
from evdown_torch.transforms.functional.compiled.regions import (
    columns_of,
    outside_error,
    region_tables,
)
from evdown_torch.transforms.functional.compiled.scratch import kept_map, scratch_column

__all__ = ["SPAN_LIMIT", "decide_in_order", "last_neighbours"]

#: The most ``(t - o) / tau`` the loop lets its clock reach before moving the origin ``o`` to
#: ``t``: every scaled count stays below ``exp(500)`` times a count (``1e217`` times it).
SPAN_LIMIT = 500.0

#: Relative rounding of one float64 operation.
EPS = 2.0**-53

#: Counts the loop can no longer hold are dropped: scaled below the smallest float64, or by
#: a factor below ``exp(-745)`` at a move of the origin (then at most ``exp(500 - 745)``
#: times a count). A count is below ``2**63``, so what they would add to a density (at
#: least 1) is below this.
_LOST = 1e-70


@compiled_loop
def _last_loop(
    key: np.ndarray, place: np.ndarray, shifts: np.ndarray, planes: int, latest: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Each grouped event's neighbours' last events, sweeping the events in stream order.

    ``out[d, g]``: 1 + the grouped place of the last event at ``key[g] + shifts[d]`` up to
    grouped event ``g`` in stream order (0: none); ``place[e]``: stream event ``e``'s.
    """
    latest[:] = 0
    for e in range(place.shape[0]):
        g = place[e]
        pixel = key[g]
        latest[np.uint64(pixel)] = g + 1
        for d in range(shifts.shape[0]):
            neighbour = pixel + shifts[d]
            if 0 <= neighbour < planes:
                out[d, g] = latest[np.uint64(neighbour)]
            else:
                out[d, g] = 0


def last_neighbours(key: Tensor, place: Tensor, shifts: Tensor, planes: int) -> Tensor:
    """The neighbours' last events, as the eager search finds them where they exist.

    Args:
        key: ``(N,)`` int64 padded pixel key of each event, grouped (by pixel, then stream
            position), each in ``0 .. planes - 1``.
        place: ``(N,)`` int64 grouped place of each event in stream order.
        shifts: ``(D,)`` int64 key offsets of the neighbours.
        planes: the keys' range.

    Returns:
        ``(D, N)`` int64: for offset ``d`` and grouped event ``g``, 1 + the grouped place of
        the neighbour's last event up to ``g`` in stream order, 0 where it has none (the
        places in the eager kernel's arrays, which hold a sentinel in front).
    """
    keys, places, offsets = columns_of(key, place, shifts)
    out = np.empty((offsets.shape[0], keys.shape[0]), dtype=np.int64)
    _last_loop(keys, places, offsets, planes, np.empty(planes, dtype=np.int64), out)
    return torch.from_numpy(out)


@inlined_helper
def _padded_key(x: int, y: int, on: bool, padded_width: int, padded_height: int,
                r: int) -> int:  # pragma: no cover - compiled
    """A pixel's and polarity's key on the sensor padded by ``r`` (``density._pixel_keys``)."""
    return ((padded_height if on else 0) + y + r) * padded_width + x + r


@inlined_helper
def _scaled(count: float, last: float, origin: float,
            tau: float) -> float:  # pragma: no cover - compiled
    """``count * exp((last - origin) / tau)``: a state's count scaled to the origin.

    ``origin`` is not earlier than ``last`` where there is a count (the stream is
    time-sorted), so no factor exceeds 1; an integer difference is exact.
    """
    return count * math.exp((last - origin) / tau) if count > 0 else 0.0


@compiled_loop
def _scaled_counts(decayed: np.ndarray, last_t: np.ndarray, origin: float, tau: float,
                   scaled: np.ndarray, live: np.ndarray, listed: np.ndarray, call: int,
                   ) -> int:  # pragma: no cover - compiled
    """Every pixel's count scaled to ``origin`` (:func:`_scaled`), and the pixels where not 0.

    Writes the live pixels' indices to ``live`` and ``call`` at their ``listed``; returns
    their number.
    """
    n_live = 0
    for j in range(decayed.shape[0]):
        value = _scaled(decayed[j], last_t[j], origin, tau)
        scaled[j] = value
        if value > 0:
            listed[j] = call
            live[n_live] = j
            n_live += 1
    return n_live


@compiled_loop
def _scaled_patches(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, width: int, height: int, r: int,
    shifts: np.ndarray, decayed: np.ndarray, last_t: np.ndarray, origin: float, tau: float,
    scaled: np.ndarray, live: np.ndarray, listed: np.ndarray, ready: np.ndarray, call: int,
) -> tuple[int, float]:  # pragma: no cover - compiled
    """:func:`_scaled_counts` of the pixels in the events' patches only: the same values.

    For a chunk whose patches cover less than the sensor; the loop reads no other pixel's
    count. Each pixel scaled gets ``call`` at its ``ready``, and is scaled once. Returns
    the live pixels' number and the largest count among the patches' (every event's own
    pixel's among them). Events outside the sensor are skipped (the loop refuses them).
    """
    wp = width + 2 * r
    hp = height + 2 * r
    n_live = 0
    largest = 0.0
    for i in range(x.shape[0]):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi < 0 or xi >= width or yi < 0 or yi >= height:
            continue
        key = _padded_key(xi, yi, p[i], wp, hp, r)
        for d in range(shifts.shape[0]):
            at = np.uint64(key + shifts[d])
            if ready[at] == call:
                continue
            ready[at] = call
            value = _scaled(decayed[at], last_t[at], origin, tau)
            scaled[at] = value
            largest = max(largest, decayed[at])
            if value > 0:
                listed[at] = call
                live[n_live] = at
                n_live += 1
    return n_live, largest


@inlined_helper
def _row_sum(scaled: np.ndarray, at: int, r: int,
             g: np.ndarray) -> float:  # pragma: no cover - compiled
    """``sum_e g[e] * scaled[at - r + e]``: a patch row's weighted counts, in ``e`` order.

    Positions outside the map are skipped (they hold no count: the sensor is padded by ``r``).
    """
    total = 0.0
    for e in range(g.shape[0]):
        near = at - r + e
        if 0 <= near < scaled.shape[0]:
            total += g[e] * scaled[np.uint64(near)]
    return total


@compiled_loop
def _all_row_sums(scaled: np.ndarray, r: int, g: np.ndarray,
                  rows: np.ndarray) -> None:  # pragma: no cover - compiled
    """Every position's row sum (:func:`_row_sum`) into ``rows``."""
    for at in range(scaled.shape[0]):
        rows[at] = _row_sum(scaled, at, r, g)


@compiled_loop
def _subsample_loop(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, t: np.ndarray, u: np.ndarray, s: float,
    rate: float, width: int, height: int, r: int, shifts: np.ndarray, weights: np.ndarray,
    scaled: np.ndarray, live: np.ndarray, n_live: int, listed: np.ndarray, call: int,
    by_rows: bool, g: np.ndarray, rows: np.ndarray, decayed: np.ndarray,
    last_t: np.ndarray, origin: float, relative: float, column: np.ndarray, row: np.ndarray,
    out_x: np.ndarray, out_y: np.ndarray, out_t: np.ndarray, out_p: np.ndarray,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """Decide each time-sorted event, in stream order: kept iff ``u[i] < s * density``.

    ``rate``: ``1 / tau`` (0 for no decay). ``scaled``: each padded pixel's count scaled
    to ``origin`` (:func:`_scaled_counts`, or :func:`_scaled_patches` for the patches the
    loop reads), updated; ``live[:n_live]``: the pixels where it is not 0 (``call`` at their
    ``listed``), the only ones a move of the origin shrinks (each
    drops out once its count underflows, at most three moves after its last event: a move
    costs its live pixels, not the sensor). The patch sum: with ``by_rows``, by the row sums
    ``rows`` (each position's, :func:`_all_row_sums`, ``g`` the weights along one axis:
    ``w = g(dx) g(dy)``), updated as counts grow and made again when the origin moves; else
    the ``k * k`` neighbours at ``shifts`` with their ``weights``. ``decayed`` and
    ``last_t``: the state's
    columns, updated at each event's pixel. ``relative``: the relative bound of both paths'
    roundings (:func:`_doubt_bound`), to which each move of the origin adds its own. The
    kept events' regions (by the tables ``column`` and ``row``), ``t`` and ``p`` are written
    at ``0, 1, ...`` of ``out_*``.

    Returns:
        ``(status, kept)``: status -1 after the last event; ``i >= 0`` for an event in doubt
        (its draw within the bound of ``s * density``: the call goes to the eager kernel);
        ``-2 - i`` for an event outside the sensor.
    """
    wp = width + 2 * r
    hp = height + 2 * r
    moved = 0.0  # the relative rounding the origin's moves add
    kept = 0
    m = shifts.shape[0]
    rise, fall = 1.0, 1.0
    for i in range(t.shape[0]):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi < 0 or xi >= width or yi < 0 or yi >= height:
            return -2 - i, kept
        ti = t[i]
        elapsed = (ti - origin) * rate
        if elapsed > SPAN_LIMIT:  # move the origin to ti; counts that underflow drop out
            shrink = math.exp(-elapsed)
            n_kept = 0
            for j in range(n_live):
                pixel = np.uint64(live[j])
                value = scaled[pixel] * shrink
                scaled[pixel] = value
                if value > 0:
                    live[n_kept] = pixel
                    n_kept += 1
                else:
                    listed[pixel] = 0
            n_live = n_kept
            if by_rows:  # the row sums again, from the shrunk counts
                _all_row_sums(scaled, r, g, rows)
            moved += (3 * min(elapsed, 745.0) + 4) * EPS
            origin = ti
            elapsed = 0.0
        # exp((t - o) / tau) and its inverse, once a time: events of one time come in runs
        # (about 25 a microsecond at 25 M events/s), and the origin never moves inside one
        # (its first event moves it to their time, if any does)
        if i == 0 or ti != t[i - 1]:
            rise = math.exp(elapsed)
            fall = 1.0 / rise
        key = _padded_key(xi, yi, p[i], wp, hp, r)
        at = np.uint64(key)
        if listed[at] != call:
            listed[at] = call
            live[n_live] = key
            n_live += 1
        own = scaled[at] + rise
        scaled[at] = own
        decayed[at] = own * fall
        last_t[at] = ti
        total = 0.0
        if by_rows:  # this event's count enters the k row sums around it; the density
            # reads the k row sums of its column (w = g(dx) g(dy))
            for e in range(g.shape[0]):
                rows[np.uint64(key - r + e)] += g[e] * rise
            for e in range(g.shape[0]):
                total += g[e] * rows[np.uint64(key + (e - r) * wp)]
        else:  # the k * k neighbours in four chains of additions (each a fixed order): the
            # additions of one chain wait for each other, those of four overlap
            a0, a1, a2, a3 = 0.0, 0.0, 0.0, 0.0
            d = 0
            while d + 4 <= m:
                a0 += weights[d] * scaled[np.uint64(key + shifts[d])]
                a1 += weights[d + 1] * scaled[np.uint64(key + shifts[d + 1])]
                a2 += weights[d + 2] * scaled[np.uint64(key + shifts[d + 2])]
                a3 += weights[d + 3] * scaled[np.uint64(key + shifts[d + 3])]
                d += 4
            while d < m:
                a0 += weights[d] * scaled[np.uint64(key + shifts[d])]
                d += 1
            total = (a0 + a1) + (a2 + a3)
        bar = s * (total * fall)
        if abs(u[i] - bar) <= bar * (relative + moved) + _LOST:
            return i, kept
        # Every event is written at ``kept``, which moves on past a kept one only.
        out_x[kept] = column[np.uint64(xi)]
        out_y[kept] = row[np.uint64(yi)]
        out_t[kept] = ti
        out_p[kept] = p[i]
        kept += u[i] < bar
    return -1, kept


def _patches_only(n: int, patch: int, planes: int) -> bool:
    """Whether ``n`` events' patches of ``patch`` pixels cover less than the ``planes``.

    Then only their pixels' counts are scaled (:func:`_scaled_patches`), else every pixel's
    (:func:`_scaled_counts`, one pass without a check a pixel): the same values either way.
    """
    return n * patch < planes


def _by_rows(n: int, k: int, planes: int) -> bool:
    """Whether ``n`` events' patches of ``k x k`` are summed by rows (:func:`_subsample_loop`).

    Making every position's row sum costs ``k`` terms a position; the rows save an event
    ``k * k - 2 * k`` terms, each about half a row sum's (read at random, not in order). So
    the rows where ``2 k * planes <= n * (k * k - 2 k)``: a live chunk of a small sensor,
    not a few events on a large one (where the patches' ``k * k`` neighbours cost less).
    """
    return 2 * k * planes <= n * (k * k - 2 * k)


def _doubt_bound(n: int, k: int, largest_count: float, by_rows: bool) -> float:
    """Twice the two paths' relative roundings of ``s * density`` in a call of ``n`` events.

    Relative to the exact density of the call's events from the state it starts from, in
    units of ``EPS`` (``2**-53``):

    * the loop: a count scaled from the state (``2 * 745 + 4``: a decay's exponent is
      rounded twice, ``exp`` and the product once each; older counts are lost, ``_LOST``),
      ``exp((t - o) / tau)`` twice (``3 * 500 + 3`` each: its exponent, at most
      :data:`SPAN_LIMIT`, is rounded three times, as ``(t - o) * (1 / tau)``; then its
      inverse), one addition an event at a pixel (``n``), the patch sum, the products by
      the inverse and by ``s``; each move of the origin adds its own (in the loop). The
      patch sum: by the ``k * k`` neighbours, their additions and products (``k * k``, and
      10 for the rest); by rows (``by_rows``), a row sum's ``k`` products and additions when
      made, one product and addition an event in the row (``k + n + 1``; a move of the
      origin makes it again from the shrunk counts), the column's ``k`` products and
      additions (``k + 1``), the weights ``g(dx) g(dy)`` against the exact ``w`` (4: each
      ``g`` within an ulp), and 10 for the rest;
    * the eager kernel: its doubling scan, ``(2 L + 2)`` times one plus the terms'
      size-weighted mean age in units of ``tau`` (docs/semantics.md; ``L`` the scan's
      passes, ``ceil(log2 n) + 1`` with the carried count; the mean age is below
      ``(n + largest carried count) / e``, as ``a exp(-a) <= 1 / e`` and the newest term is
      1), each neighbour's decay to the event (``2 * 745 + 4``), its patch sums and ``s``.
    """
    passes = math.ceil(math.log2(n + 1)) + 1
    patch = n + 2 * k + 16 if by_rows else k * k + 10
    loop = (2 * 745 + 4) + 2 * (3 * SPAN_LIMIT + 3) + n + patch
    eager = (2 * passes + 2) * (1 + (n + largest_count) / math.e) + (2 * 745 + 4) + k * k + 8
    return 2 * (loop + eager) * EPS


def decide_in_order(
    events: Events, decayed: Tensor, last_t: Tensor, draws: Tensor, *,
    sensor_size: tuple[int, int, int], factor: tuple[int, int], tau: float, s: float,
    radius: int, shifts: Tensor, weights: Tensor, axis: Tensor, clock_start: int | float,
) -> tuple[Events, Tensor, Tensor] | None:
    """:func:`~..density.density_step`'s decisions of ``N >= 1`` time-sorted events on the CPU.

    Args:
        events: the chunk, time-sorted, on the CPU.
        decayed: ``(2 * H' * W',)`` float64 the state's counts on the padded sensor
            (:class:`~..density.DensityState`; not written).
        last_t: ``(2 * H' * W',)`` the state's times of each pixel's last event (not
            written).
        draws: ``(N,)`` float64 each event's draw.
        sensor_size: ``(W, H, P)``.
        factor: ``(fx, fy)``.
        tau: the decay time constant (``math.inf``: no decay).
        s: the budget setting.
        radius: the patch's radius ``r`` (the state's sensor is padded by it on every side).
        shifts: ``(k * k,)`` int64 the patch's key offsets on the padded sensor.
        weights: ``(k * k,)`` float64 their weights (:func:`~..density.patch_offsets`).
        axis: ``(k,)`` float64 the patch's weights along one axis
            (:func:`~..density.axis_weights`: ``w = g(dx) * g(dy)``).
        clock_start: the stream's first timestamp.

    Returns:
        ``(kept, decayed, last_t)``: the kept events downsampled (the eager kernel's), and the
        new state's columns (the loop's counts: see the module); ``None`` where the eager
        kernel must decide the call: an event in doubt, or an integer clock whose
        differences over the stream could leave int64 (``2**62`` or more since its start).

    Raises:
        ValueError: for an event whose pixel lies outside the sensor.
    """
    n = events.num_events
    t = events.t
    width, height, _ = sensor_size
    if t.dtype == torch.int64 and t[-1].item() - int(clock_start) >= 1 << 62:
        return None
    counts = decayed.numpy().copy()
    times = last_t.numpy().copy()
    planes = counts.shape[0]
    k = 2 * radius + 1
    by_rows = _by_rows(n, k, planes)
    # each position's row sum, made anew each call (:func:`_all_row_sums`)
    rows = scratch_column("density rows", planes if by_rows else 0, np.float64)
    # Per-pixel maps kept from call to call (taking them new would cost the sensor's area a
    # call): the scaled counts, and the number of the call that listed a pixel as live
    # (``listed``, the last call's number at its end) or scaled it (``ready``), so none is
    # cleared.
    with kept_map("density scaled", planes, np.float64) as scaled, \
            kept_map("density listed", planes + 1, np.int64) as listed, \
            kept_map("density ready", planes, np.int64) as ready:
        call = int(listed[-1]) + 1
        listed[-1] = call
        origin = t.numpy()[0]
        x, y, p = columns_of(events.x, events.y, events.p)
        g = axis.numpy()
        if _patches_only(n, k * k, planes):
            live = scratch_column("density live", n * k * k, np.int64)
            n_live, largest = _scaled_patches(
                x, y, p, width, height, radius, shifts.numpy(), counts, times, origin, tau,
                scaled, live, listed[:-1], ready, call)
        else:
            live = scratch_column("density live", planes, np.int64)
            n_live = _scaled_counts(counts, times, origin, tau, scaled, live, listed[:-1],
                                    call)
            largest = float(counts.max())
        if by_rows:
            _all_row_sums(scaled, radius, g, rows)
        out_w, out_h, _ = output_size(sensor_size, factor)
        column, row = region_tables(factor, out_w, out_h)
        out_x, out_y = (scratch_column(f"density {name}", n, np.int64) for name in ("x", "y"))
        out_t = scratch_column("density t", n, t.numpy().dtype)
        out_p = scratch_column("density p", n, np.bool_)
        status, kept = _subsample_loop(
            x, y, p, t.numpy(), draws.numpy(), s, 1.0 / tau, width, height, radius,
            shifts.numpy(), weights.numpy(), scaled, live, n_live, listed[:-1], call, by_rows,
            g, rows, counts, times, origin, _doubt_bound(n, k, largest, by_rows),
            column, row, out_x, out_y, out_t, out_p)
    if status >= 0:
        return None
    if status < -1:
        raise outside_error(-2 - status, x, y, np.empty(width, np.int8),
                            np.empty(height, np.int8))
    output = Events(*(torch.from_numpy(c[:kept]) for c in (out_x, out_y, out_t, out_p)))
    return output, torch.from_numpy(counts), torch.from_numpy(times)
