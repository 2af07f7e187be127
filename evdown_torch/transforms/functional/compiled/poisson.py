"""PoissonSubsampling's step compiled: one pass over the events, in stream order.

The eager kernel (:mod:`..poisson`) builds a sparse count table of the chunk's windows, blurs
each previous window's map along rows for all its entries, gathers the columns at every
entry and applies the cap by a cumulative minimum. This loop keeps the counts of the current
window and of the one before as dense maps (taken from the state's entries), and when a
window starts, spreads each of the previous window's entries ``g(dx) * (1 - exp(-n))`` along
its row (the row blur) and adds up the window's ``mean B``; an event's ``B`` then gathers its
column's 13 row sums once per pixel and window. The cap runs event by event in integers, as
the eager kernel's closed form computes it. The dense maps stay with the thread from call to call
(:func:`~.scratch.kept_map`): each call zeroes what it wrote, and numbers its windows above
all those before, so a call costs its chunk's pixels, not the sensor's area.

The two paths add their sums in other orders, and ``1 - exp(-n)`` may differ by an ulp: the
loop bounds both paths' roundings of ``P`` (:func:`_doubt_bound`), and an event whose draw lies
within that bound of its ``P`` hands the call to the eager kernel, so both paths keep the same
events. The counts and the state are integers: the same on both paths.
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
from evdown_torch.transforms.functional.compiled.sorting import stable_order

__all__ = ["decide_in_order"]

#: Relative rounding of one float64 operation.
EPS = 2.0**-53

#: :func:`_clear_blur` clears the whole blur map where it has at most this many entries per
#: entry the blur wrote: on the live replay's 128x128 sensor, the scattered zeros of two
#: windows' blur took about 0.6 ms of a 4.4 ms call.
WHOLE_CLEAR = 4

#: Counts below this take ``1 - exp(-n)`` from a table (:func:`_start_window`).
_TABLED = 64


@inlined_helper
def _clear_keys(counts: np.ndarray, keys: np.ndarray, n: int) -> None:  # pragma: no cover
    """Zeros in ``counts`` at ``keys[:n]``: a window's map as the next window takes it."""
    for m in range(n):
        counts[np.uint64(keys[m])] = 0


@inlined_helper
def _clear_blur(rows: np.ndarray, blurred_from: np.ndarray, n_blurred: int, width: int,
                radius: int) -> None:  # pragma: no cover - compiled
    """Zeros in ``rows`` where the blur of the entries ``blurred_from[:n_blurred]`` wrote.

    The whole map at once where that is at most :data:`WHOLE_CLEAR` times the entries'
    writes (a map of a small sensor): one pass in order rather than scattered writes.
    """
    if WHOLE_CLEAR * n_blurred * (2 * radius + 1) >= rows.shape[0]:
        rows[:] = 0.0
        return
    for m in range(n_blurred):
        key = blurred_from[m]
        x = key % width
        for d in range(2 * radius + 1):
            if 0 <= x + d - radius < width:
                rows[np.uint64(key + d - radius)] = 0.0


@compiled_loop
def _start_window(
    counts: np.ndarray, entries: np.ndarray, n_entries: int, width: int, height: int,
    g: np.ndarray, spread_x: np.ndarray, spread_y: np.ndarray, rows: np.ndarray,
    blurred_from: np.ndarray, n_blurred: int, mass: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """The previous window's row blur and mass, from its entries, the last blur cleared.

    ``counts[entries[:n_entries]]``: the previous window's counts. ``rows`` holds the blur
    of the entries ``blurred_from[:n_blurred]`` (cleared here, then those become
    ``entries``): each entry's ``g(dx) * (1 - exp(-n))`` added at ``dx`` columns from it,
    inside the sensor, in the entries' order. ``mass[p]``: ``sum (1 - exp(-n)) * spread_x *
    spread_y`` over the polarity's entries. Returns the new ``n_blurred``.
    """
    radius = g.shape[0] // 2
    _clear_blur(rows, blurred_from, n_blurred, width, radius)
    mass[0] = 0.0
    mass[1] = 0.0
    tabled = np.empty(_TABLED)  # 1 - exp(-n) of the small counts, as below
    for n in range(_TABLED):
        tabled[n] = -math.expm1(-np.float64(n))
    for m in range(n_entries):
        key = entries[m]
        blurred_from[m] = key
        count = counts[np.uint64(key)]
        value = tabled[count] if count < _TABLED else -math.expm1(-np.float64(count))
        x = key % width
        y = (key // width) % height
        mass[key // (width * height)] += value * spread_x[x] * spread_y[y]
        for d in range(g.shape[0]):
            if 0 <= x + d - radius < width:
                rows[np.uint64(key + d - radius)] += g[d] * value
    return n_entries


@compiled_loop
def _restore(
    current: np.ndarray, cur_keys: np.ndarray, n_cur: int, previous: np.ndarray,
    prev_keys: np.ndarray, n_prev: int, rows: np.ndarray, blurred_from: np.ndarray,
    n_blurred: int, width: int, radius: int,
) -> None:  # pragma: no cover - compiled
    """The maps as the next call takes them (:func:`decide_in_order`): zeros where a call wrote."""
    _clear_keys(current, cur_keys, n_cur)
    _clear_keys(previous, prev_keys, n_prev)
    _clear_blur(rows, blurred_from, n_blurred, width, radius)


@compiled_loop
def _window_events(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, window: np.ndarray, u: np.ndarray, i: int,
    alpha: float, a: int, b: int, limit: int, remainder: int, kept: int, width: int,
    height: int, g: np.ndarray, norm_x: np.ndarray, norm_y: np.ndarray, mass: np.ndarray,
    current: np.ndarray, cur_keys: np.ndarray, n_cur: int, rows: np.ndarray,
    chances: np.ndarray, stamp: np.ndarray, epoch: int, bound: float, column: np.ndarray,
    row: np.ndarray, t: np.ndarray, out_x: np.ndarray, out_y: np.ndarray, out_t: np.ndarray,
    out_p: np.ndarray, n_out: int,
) -> tuple[int, int, int, int, int, int, int]:  # pragma: no cover - compiled
    """Decide the events of one window, from event ``i`` to the window's last in the chunk.

    A function of its own, not the body of :func:`_poisson_loop`'s loop: there the maps
    are swapped as windows start, and an array variable assigned inside a loop made every
    event's reads and writes of it about twice as slow (``_numba``, "No array assigned in
    a hot loop"). ``mass``: the previous window's ``mean B`` numerators by polarity;
    ``bound``: the window's doubt bound; the rest as :func:`_poisson_loop`'s.

    Returns:
        ``(status, next event, limit, remainder, kept, n_cur, n_out)``: status -1 at the
        window's end (or the chunk's), else as :func:`_poisson_loop`'s.
    """
    radius = g.shape[0] // 2
    area = float(width * height)
    w = window[i]
    n = window.shape[0]
    while i < n and window[i] == w:
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi < 0 or xi >= width or yi < 0 or yi >= height:
            return -2 - i, i, limit, remainder, kept, n_cur, n_out
        key = ((1 if p[i] else 0) * height + yi) * width + xi
        at = np.uint64(key)
        if stamp[at] != epoch:  # the pixel's P in this window, once
            mean = mass[1 if p[i] else 0] / area
            if mean > 0:  # (0 where the previous window has no entry)
                total = 0.0
                for d in range(g.shape[0]):
                    if 0 <= yi + d - radius < height:
                        total += g[d] * rows[np.uint64(key + (d - radius) * width)]
                blurred = total / (norm_x[xi] * norm_y[yi])
                chances[at] = min(alpha * (blurred / mean), 1.0)
            else:
                chances[at] = alpha
            stamp[at] = epoch
        chance = chances[at]
        ui = u[i]
        if abs(ui - chance) <= chance * bound + 1e-300:
            return i, i, limit, remainder, kept, n_cur, n_out
        # the cap: floor(a * seen / b) after this event, one step of a <= b at a time
        remainder += a
        if remainder >= b:
            remainder -= b
            limit += 1
        if ui < chance and kept < limit:
            kept += 1
            out_x[n_out] = column[np.uint64(xi)]
            out_y[n_out] = row[np.uint64(yi)]
            out_t[n_out] = t[i]
            out_p[n_out] = p[i]
            n_out += 1
        if current[at] == 0:
            cur_keys[n_cur] = key
            n_cur += 1
        current[at] += 1
        i += 1
    return -1, i, limit, remainder, kept, n_cur, n_out


@compiled_loop
def _poisson_loop(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, window: np.ndarray, u: np.ndarray,
    alpha: float, a: int, b: int, limit: int, remainder: int, kept: int, width: int,
    height: int, g: np.ndarray, norm_x: np.ndarray, norm_y: np.ndarray, spread_x: np.ndarray,
    spread_y: np.ndarray, current: np.ndarray, previous: np.ndarray, cur_keys: np.ndarray,
    n_cur: int, prev_keys: np.ndarray, n_prev: int, cur_window: int, rows: np.ndarray,
    blurred_from: np.ndarray, chances: np.ndarray, stamp: np.ndarray, epoch: int,
    relative: float, column: np.ndarray, row: np.ndarray, t: np.ndarray, out_x: np.ndarray,
    out_y: np.ndarray, out_t: np.ndarray, out_p: np.ndarray,
) -> tuple[int, int, int, np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, int, int, int,
           int]:  # pragma: no cover - compiled
    """Decide each time-sorted event: a candidate iff ``u < P``, kept iff the cap allows.

    Window by window: the previous window's blur and mean when one starts, then its
    events (:func:`_window_events`). ``current`` / ``previous``: dense counts of window
    ``cur_window`` and of the one before, their keys in ``cur_keys[:n_cur]`` and
    ``prev_keys[:n_prev]``; swapped as windows start. ``limit``, ``remainder``:
    ``divmod(a * seen, b)``, moved on an event at a time; ``kept``: the cap's count.
    ``chances``: each pixel's ``P`` in the window it was last computed in, whose number is
    the pixel's ``stamp``; ``epoch``: the largest number in ``stamp`` (each window of the
    call takes the next one, so no ``stamp`` is cleared). The kept events' regions, ``t``
    and ``p`` go to ``out_*``.

    Returns:
        ``(status, kept events, kept, current, cur_keys, n_cur, previous, prev_keys, n_prev,
        cur_window, n_blurred, epoch)``: status -1 after the last event, ``i >= 0`` for an
        event in doubt (the call goes to the eager kernel), ``-2 - i`` for an event outside
        the sensor; the maps as they end (swapped as windows started), the entries whose
        blur ``rows`` holds (``blurred_from[:n_blurred]``) and the last window's number.
    """
    mass = np.zeros(2)
    # (np.int64, not a literal 0: one compile of each loop called, not two)
    n_blurred, n_out, i = np.int64(0), np.int64(0), np.int64(0)
    status = -1
    while i < window.shape[0] and status == -1:
        w = window[i]
        if w != cur_window:  # a new window: the current one becomes the previous, or none
            _clear_keys(previous, prev_keys, n_prev)
            if w == cur_window + 1:
                current, previous = previous, current
                cur_keys, prev_keys = prev_keys, cur_keys
                n_prev, n_cur = n_cur, 0
            else:
                _clear_keys(current, cur_keys, n_cur)
                n_prev, n_cur = 0, 0
            cur_window = w
        # the previous window's blur and mean, once a window
        n_blurred = _start_window(previous, prev_keys, n_prev, width, height, g, spread_x,
                                  spread_y, rows, blurred_from, n_blurred, mass)
        epoch += 1
        status, i, limit, remainder, kept, n_cur, n_out = _window_events(
            x, y, p, window, u, i, alpha, a, b, limit, remainder, kept, width, height, g,
            norm_x, norm_y, mass, current, cur_keys, n_cur, rows, chances, stamp, epoch,
            relative * (n_prev + 64), column, row, t, out_x, out_y, out_t, out_p, n_out)
    return (status, n_out, kept, current, cur_keys, n_cur, previous, prev_keys, n_prev,
            cur_window, n_blurred, epoch)


def _sorted(keys: np.ndarray) -> np.ndarray:
    """``keys`` (int64) in increasing order, a new array: ``np.sort``'s, by the radix sort.

    :func:`~.sorting.stable_order` took 0.08 ms on a window's 15,000 keys where ``np.sort``
    took 0.40 ms.
    """
    return keys[stable_order(keys)]


@compiled_loop
def _merge_loop(head: np.ndarray, tail: np.ndarray, out: np.ndarray) -> bool:  # pragma: no cover
    """The merge of increasing ``head`` and increasing ``tail``, written into ``out``.

    Returns:
        ``True``; ``False`` (``out`` not all written) where ``head`` is not increasing.
    """
    i, j = 0, 0
    for k in range(out.shape[0]):
        if j == tail.shape[0] or (i < head.shape[0] and head[i] <= tail[j]):
            if i > 0 and head[i] <= head[i - 1]:  # (each head key checked as it is taken)
                return False
            out[k] = head[i]
            i += 1
        else:
            out[k] = tail[j]
            j += 1
    return True


def _sorted_after(keys: np.ndarray, head: int) -> np.ndarray:
    """:func:`_sorted` of ``keys``, whose first ``head`` are increasing already (else sorted).

    A window's entries are the state's of that window (increasing: the state's order), then
    the keys its events added: only those are sorted, and merged. On a large sensor a window
    can hold every pixel: sorting them all again at every call took 13 ms for 921,600 keys on
    1280x720, where the merge is one pass.
    """
    if head == 0:
        return _sorted(keys)
    out = np.empty(keys.shape[0], np.int64)
    if _merge_loop(keys[:head], _sorted(keys[head:]), out):
        return out
    return _sorted(keys)  # (a state whose entries are not in order: sorted like the eager)


def _doubt_bound() -> float:
    """Twice both paths' relative roundings of ``P``, per entry of the previous window.

    The loop returns ``relative * (entries + 64)``. Each path: ``1 - exp(-n)`` within an ulp
    (2), a row sum of at most 13 positive products (14) and its 13 weighted terms gathered
    (14), the norms' product and the division (2), ``mean B``'s sum over the entries (one
    addition an entry) and its three products and division (4), the ratio and ``alpha``
    (2): ``entries + 38`` units of ``EPS``; the same for the other path, twice.
    """
    return 4 * EPS


def decide_in_order(
    events: Events, window: Tensor, draws: Tensor, entry_windows: Tensor, entry_keys: Tensor,
    entry_counts: Tensor, *, sensor_size: tuple[int, int, int], factor: tuple[int, int],
    alpha: float, fraction: tuple[int, int], seen: int, kept: int, blur: tuple[float, ...],
    edges: tuple[Tensor, Tensor, Tensor, Tensor],
) -> tuple[Events, int, Tensor, Tensor, Tensor] | None:
    """:func:`~..poisson.poisson_step`'s decisions of ``N >= 1`` time-sorted events on the CPU.

    Args:
        events: the chunk, time-sorted, on the CPU.
        window: ``(N,)`` int64 each event's window.
        draws: ``(N,)`` float64 each event's draw.
        entry_windows: ``(E,)`` int64 the state's entries' windows.
        entry_keys: ``(E,)`` int64 their keys ``(p * H + y) * W + x``.
        entry_counts: ``(E,)`` int64 their counts.
        sensor_size: ``(W, H, P)``.
        factor: ``(fx, fy)``.
        alpha: the budget setting.
        fraction: ``(a, b)``, the cap's fraction (``a <= b``).
        seen: the events seen before the chunk.
        kept: the events kept before the chunk.
        blur: the 13 weights of the Gaussian.
        edges: ``(norm_x, spread_x, norm_y, spread_y)`` float64 (the eager kernel's).

    Returns:
        ``(kept events, kept count, windows, keys, counts)``: the eager kernel's events and
        the new state's entries (the last window's and the one before, sorted by window,
        then key); ``None`` where an event is in doubt.

    Raises:
        ValueError: for an event whose pixel lies outside the sensor.
    """
    n = events.num_events
    width, height, _ = sensor_size
    planes = 2 * width * height
    # A window's entries: the state's of that window, then at most one an event.
    most = min(planes, n + entry_keys.shape[0])
    cur_keys, prev_keys, blurred_from = (scratch_column(f"poisson {name}", most, np.int64)
                                         for name in ("current keys", "previous keys",
                                                      "blurred from"))
    first = int(window[0])
    a, b = fraction
    limit, remainder = divmod(a * seen, b)
    out_w, out_h, _ = output_size(sensor_size, factor)
    column, row = region_tables(factor, out_w, out_h)
    x, y, p, t = columns_of(events.x, events.y, events.p, events.t)
    out_x, out_y = (scratch_column(f"poisson {name}", n, np.int64) for name in ("x", "y"))
    out_t, out_p = scratch_column("poisson t", n, t.dtype), scratch_column("poisson p", n, p.dtype)
    norm_x, spread_x, norm_y, spread_y = (edge.numpy() for edge in edges)
    g = np.array(blur)

    def seeded(counts: np.ndarray, keys: np.ndarray, chosen: np.ndarray) -> int:
        """The state's entries ``chosen`` put in ``counts``, their keys in ``keys``."""
        found = entry_keys.numpy()[chosen]
        counts[found] = entry_counts.numpy()[chosen]
        keys[:found.shape[0]] = found
        return found.shape[0]

    # Per-pixel maps kept from call to call as each call leaves them (a call touches its
    # chunk's pixels only): the counts and the blur zero outside a call, each pixel's
    # ``P`` and window number, the last number at the end of ``stamp``.
    with kept_map("poisson current", planes, np.int64) as current, \
            kept_map("poisson previous", planes, np.int64) as previous, \
            kept_map("poisson rows", planes, np.float64) as rows, \
            kept_map("poisson chances", planes, np.float64) as chances, \
            kept_map("poisson stamp", planes + 1, np.int64) as stamp:
        n_cur = seeded_cur = seeded(current, cur_keys, entry_windows.numpy() == first)
        n_prev = seeded_prev = seeded(previous, prev_keys, entry_windows.numpy() == first - 1)
        (status, n_out, kept_after, last_current, cur_keys, n_cur, last_previous, prev_keys,
         n_prev, last, n_blurred, stamp[-1]) = _poisson_loop(
            x, y, p, window.numpy(), draws.numpy(), alpha, a, b, limit, remainder, kept, width,
            height, g, norm_x, norm_y, spread_x, spread_y, current, previous, cur_keys, n_cur,
            prev_keys, n_prev, first, rows, blurred_from, chances, stamp[:-1], int(stamp[-1]),
            _doubt_bound(), column, row, t, out_x, out_y, out_t, out_p)
        # The new state: the entries of the last window and of the one before, by window, key.
        # Each window's keys start with the state's of that window, in order: a window that
        # the call started in keeps its seeded keys first, also once it became the previous.
        head_prev, head_cur = {0: (seeded_prev, seeded_cur), 1: (seeded_cur, 0)}.get(
            last - first, (0, 0))
        before = _sorted_after(prev_keys[:n_prev], head_prev)
        after = _sorted_after(cur_keys[:n_cur], head_cur)
        counts = np.concatenate([last_previous[before], last_current[after]])
        _restore(last_current, cur_keys, n_cur, last_previous, prev_keys, n_prev, rows,
                 blurred_from, n_blurred, width, g.shape[0] // 2)
    if status >= 0:
        return None
    if status < -1:
        raise outside_error(-2 - status, x, y, np.empty(width, np.int8),
                            np.empty(height, np.int8))
    output = Events(*(torch.from_numpy(part[:n_out]) for part in (out_x, out_y, out_t, out_p)))
    keys = np.concatenate([before, after])
    windows = np.concatenate([np.full(before.shape[0], last - 1, dtype=np.int64),
                              np.full(after.shape[0], last, dtype=np.int64)])
    return (output, kept_after, torch.from_numpy(windows), torch.from_numpy(keys),
            torch.from_numpy(counts))
