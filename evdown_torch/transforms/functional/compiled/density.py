"""DensitySubsampling's neighbour lookups compiled: one sweep in stream order per offset group.

:func:`~evdown_torch.transforms.functional.density._density_sorted` needs, for each event and
each offset of its patch, the neighbour pixel's last event up to this one in stream order; the
eager kernel finds it by a binary search over the events grouped by pixel (half of its time
on the live replay's chunks). This loop walks the events in stream order keeping each pixel's
latest event (its place among the grouped events) in a table, and reads the neighbours'
there: the same event wherever one exists (where none does, the eager search's answer is not
the neighbour's either, and both paths discard it), so the densities are the same, bit for
bit. The eager kernel takes it where it runs on the CPU.

A session's step on the CPU (:func:`density_step`) goes further: one loop over the events in
stream order decides each one, with no ``exp`` per neighbour. Each pixel and polarity keeps
its decayed count *scaled* to a clock origin ``o``: ``A_j = S_j * exp((t_j - o) / tau)``
(``S_j`` its count after its last event, at ``t_j``). An event at ``t`` adds
``exp((t - o) / tau)`` to its pixel's ``A``, and its density is
``sum_j w_j A_j / exp((t - o) / tau)``: one ``exp`` an event. The origin moves to the event's
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

from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import columns_of, outside_error
from evdown_torch.transforms.functional.density import (
    DensitySettings,
    DensityState,
    padded_sensor,
    patch_offsets,
)
from evdown_torch.transforms.functional.downsample import to_regions
from evdown_torch.transforms.functional.draws import event_uniforms

__all__ = ["SPAN_LIMIT", "density_step", "last_neighbours"]

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


@compiled_loop
def _scaled_counts(decayed: np.ndarray, last_t: np.ndarray, origin: float, tau: float,
                   scaled: np.ndarray, live: np.ndarray, is_live: np.ndarray,
                   ) -> int:  # pragma: no cover - compiled
    """``scaled = decayed * exp((last_t - origin) / tau)``; the pixels where it is not 0.

    ``origin`` is not earlier than any ``last_t`` of a pixel with a count (the stream is
    time-sorted), so no factor exceeds 1; an integer difference is exact. Writes the live
    pixels' indices to ``live`` and flags them in ``is_live``; returns their number.
    """
    n_live = 0
    for j in range(decayed.shape[0]):
        count = decayed[j]
        value = count * math.exp((last_t[j] - origin) / tau) if count > 0 else 0.0
        scaled[j] = value
        is_live[j] = value > 0
        if value > 0:
            live[n_live] = j
            n_live += 1
    return n_live


@compiled_loop
def _subsample_loop(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, t: np.ndarray, u: np.ndarray, s: float,
    tau: float, width: int, height: int, r: int, shifts: np.ndarray, weights: np.ndarray,
    scaled: np.ndarray, live: np.ndarray, n_live: int, is_live: np.ndarray,
    decayed: np.ndarray, last_t: np.ndarray, origin: float, relative: float, keep: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Decide each time-sorted event: ``keep[i] = u[i] < s * density``, in stream order.

    ``scaled``: each padded pixel's count scaled to ``origin`` (:func:`_scaled_counts`),
    updated; ``live[:n_live]``: the pixels where it is not 0 (flagged in ``is_live``), the
    only ones a move of the origin shrinks (each drops out once its count underflows, at
    most three moves after its last event: a move costs its live pixels, not the sensor);
    ``decayed`` and ``last_t``: the state's columns, updated at each event's pixel.
    ``relative``: the relative bound of both paths' roundings (:func:`_doubt_bound`), to
    which each move of the origin adds its own.

    Returns:
        -1 after the last event; ``i >= 0`` for an event in doubt (its draw within the bound
        of ``s * density``: the call goes to the eager kernel); ``-2 - i`` for an event
        outside the sensor.
    """
    wp = width + 2 * r
    hp = height + 2 * r
    moved = 0.0  # the relative rounding the origin's moves add
    for i in range(t.shape[0]):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi < 0 or xi >= width or yi < 0 or yi >= height:
            return -2 - i
        ti = t[i]
        elapsed = (ti - origin) / tau
        if elapsed > SPAN_LIMIT:  # move the origin to ti; counts that underflow drop out
            shrink = math.exp(-elapsed)
            kept = 0
            for m in range(n_live):
                j = np.uint64(live[m])
                value = scaled[j] * shrink
                scaled[j] = value
                if value > 0:
                    live[kept] = j
                    kept += 1
                else:
                    is_live[j] = False
            n_live = kept
            moved += (2 * min(elapsed, 745.0) + 4) * EPS
            origin = ti
            elapsed = 0.0
        rise = math.exp(elapsed)
        key = np.uint64(((hp if p[i] else 0) + yi + r) * wp + xi + r)
        if not is_live[key]:
            is_live[key] = True
            live[n_live] = key
            n_live += 1
        own = scaled[key] + rise
        scaled[key] = own
        decayed[key] = own / rise
        last_t[key] = ti
        total = 0.0
        for d in range(shifts.shape[0]):
            total += weights[d] * scaled[np.uint64(np.int64(key) + shifts[d])]
        bar = s * (total / rise)
        keep[i] = u[i] < bar
        if abs(u[i] - bar) <= bar * (relative + moved) + _LOST:
            return i
    return -1


def _doubt_bound(n: int, k: int, largest_count: float) -> float:
    """Twice the two paths' relative roundings of ``s * density`` in a call of ``n`` events.

    Relative to the exact density of the call's events from the state it starts from, in
    units of ``EPS`` (``2**-53``):

    * the loop: a count scaled from the state (``2 * 745 + 4``: a decay's exponent is
      rounded twice, ``exp`` and the product once each; older counts are lost, ``_LOST``),
      ``exp((t - o) / tau)`` twice (``2 * 500 + 3`` each: its exponent is at most
      :data:`SPAN_LIMIT`), one addition an event at a pixel (``n``), the patch's ``k * k``
      additions and products, the division and ``s``; each move of the origin adds its own
      (in the loop);
    * the eager kernel: its doubling scan, ``(2 L + 2)`` times one plus the terms'
      size-weighted mean age in units of ``tau`` (docs/semantics.md; ``L`` the scan's
      passes, ``ceil(log2 n) + 1`` with the carried count; the mean age is below
      ``(n + largest carried count) / e``, as ``a exp(-a) <= 1 / e`` and the newest term is
      1), each neighbour's decay to the event (``2 * 745 + 4``), its patch sums and ``s``.
    """
    passes = math.ceil(math.log2(n + 1)) + 1
    loop = (2 * 745 + 4) + 2 * (2 * SPAN_LIMIT + 3) + n + k * k + 8
    eager = (2 * passes + 2) * (1 + (n + largest_count) / math.e) + (2 * 745 + 4) + k * k + 8
    return 2 * (loop + eager) * EPS


def density_step(events: Events, state: DensityState, settings: DensitySettings,
                 ) -> tuple[Events, DensityState] | None:
    """:func:`~..density.density_step` of ``N >= 1`` time-sorted events on the CPU.

    The same events as the eager kernel given ``state`` (the kept ones, downsampled), and
    the new state (the loop's counts: see the module); ``state`` is not written.

    ``None`` where the eager kernel must decide the call: an event in doubt, or an integer
    clock whose differences over the stream could leave int64 (``2**62`` or more since its
    first timestamp).

    Raises:
        ValueError: for an event whose pixel lies outside the sensor.
    """
    n = events.num_events
    t = events.t
    width, height, _ = settings.sensor_size
    wp, hp, r = padded_sensor(settings)
    if t.dtype == torch.int64 and t[-1].item() - int(state.origin) >= 1 << 62:
        return None
    decayed = state.decayed.numpy().copy()
    last_t = state.last_t.numpy().copy()
    scaled = np.empty_like(decayed)
    live = np.empty(decayed.shape[0], dtype=np.int64)
    is_live = np.empty(decayed.shape[0], dtype=np.bool_)
    origin = t.numpy()[0]
    n_live = _scaled_counts(decayed, last_t, origin, settings.tau, scaled, live, is_live)
    offsets = patch_offsets(settings.k)
    shifts = np.array([dy * wp + dx for dx, dy, _ in offsets], dtype=np.int64)
    weights = np.array([w for _, _, w in offsets], dtype=np.float64)
    index = torch.arange(state.seen, state.seen + n)
    u = event_uniforms(events, settings.seed, index=index, origin=state.origin).numpy()
    largest = float(decayed.max()) if decayed.shape[0] else 0.0
    keep = np.empty(n, dtype=np.bool_)
    x, y, p = columns_of(events.x, events.y, events.p)
    status = _subsample_loop(x, y, p, t.numpy(), u, settings.s, settings.tau, width, height,
                             r, shifts, weights, scaled, live, n_live, is_live, decayed,
                             last_t, origin,
                             _doubt_bound(n, settings.k, largest), keep)
    if status >= 0:
        return None
    if status < -1:
        raise outside_error(-2 - status, x, y, np.empty(width, np.int8),
                            np.empty(height, np.int8))
    kept = to_regions(events.select(torch.from_numpy(keep)), settings.factor)
    return kept, DensityState(torch.from_numpy(decayed), torch.from_numpy(last_t),
                              state.seen + n, state.origin)
