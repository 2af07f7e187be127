"""The ramps' session as the package's state, and back: one state object on both paths.

The package's bounded-delay session keeps a
:class:`~evdown_torch.transforms.functional.estimation.stream.WindowState`: the knots the
curves after the horizon ``F`` still need (each fired pixel's last knot earlier than ``F``,
carrying its whole level, and all its knots since, held knots included), each pixel's last
knot time and each region's reference index after its last breakpoint earlier than ``F``.
:func:`window_state` builds one from a
:class:`~.linear_ramps.RampSession`, so that the package's
``estimation_step`` (eager or compiled) carries on where the ramps stopped and gives the
stream's events. The ramps' session keeps what that needs: each pixel's level and last knot time,
each region's reference index after its last change swept (its last breakpoint before
``F``) and the input events of the last ``D`` before ``F`` and since.

Of a pixel with knots at or after ``F`` (the first at ``t1``), the knot before ``F`` that the
curve needs is the start of the ramp into ``t1``: the pixel's last knot if it is at most
``D`` before ``t1`` (then among the recent events), else the held knot ``t1 - D`` (a knot of
its own, before or after ``F``). When ``t1 - D`` is at or after ``F``, the pixel is flat at
its level from its last knot to ``t1 - D``: the knot before ``F`` is placed at its region's
last breakpoint before ``F``, which is not earlier than the pixel's own last knot (that knot
was one of the region's breakpoints), so the region's curve from there on and its last
breakpoint are the package's. So is a pixel whose first knot at or after ``F`` has no level
change (a held knot handed over, events that cancel), unless that knot is at the last time:
the next chunk may still add events to it.
"""

from __future__ import annotations

import numpy as np
import torch

from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.linear_ramps import RampSession, RampSettings
from evdown_torch.transforms.functional.compiled.sorting import stable_order
from evdown_torch.transforms.functional.estimation.window_state import WindowState

__all__ = ["ramp_session", "window_state"]


@compiled_loop
def _in_time_order(
    pixel: np.ndarray, t: np.ndarray, change: np.ndarray, second: int, width: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Knots ``(pixel, t, change)`` as ``(x, y, t, change)``, in the stable sort's order of ``t``.

    The knots from ``second`` on are in time order already: the first part is sorted
    (:func:`~.sorting.stable_order`) and merged with them, the first part's first on a tie.
    """
    n = t.shape[0]
    first = stable_order(t[:second])
    out_x, out_y = np.empty(n, np.int64), np.empty(n, np.int64)
    out_t, out_change = np.empty(n, np.int64), np.empty(n, np.int64)
    i, j = 0, second
    for m in range(n):
        if j == n or (i < second and t[first[i]] <= t[j]):
            at = first[i]
            i += 1
        else:
            at = j
            j += 1
        out_x[m], out_y[m] = pixel[at] % width, pixel[at] // width
        out_t[m], out_change[m] = t[at], change[at]
    return out_x, out_y, out_t, out_change


@compiled_loop
def _knots(
    xs: np.ndarray, ys: np.ndarray, ts: np.ndarray, cs: np.ndarray, width: int,
    column: np.ndarray, row: np.ndarray, out_w: int, delay: int, t_start: int, horizon: int,
    t_last: int, last_t: np.ndarray, fired: np.ndarray, level: np.ndarray, region_t: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The state's knots ``(x, y, t, change)`` in stable time order.

    Found pixel by pixel (each fired pixel's knot before ``F``, in pixel order), then the
    knots since ``F`` in time order, and put in the order of a stable sort of both parts one
    after the other (:func:`_in_time_order`).

    ``xs``..``cs``: the knots at or after ``F - D`` (time-sorted; ``cs`` their level
    changes: the input events', or a handed-over state's, whose first knot of a pixel
    carries its whole level and held knots 0; ``F - D`` is not later than the horizon
    at the hand-over); ``last_t``: each pixel's last knot time; ``fired``: the pixel
    has a knot; ``level``: its level now; ``region_t``: each region's last breakpoint
    before ``F``.
    """
    pixels = last_t.shape[0]
    first_after = np.full(pixels, -1, np.int64)  # index of the first knot at or after F
    first_change = np.zeros(pixels, np.int64)  # that knot's level change
    last_before = np.full(pixels, -1, np.int64)  # index of the last knot before F
    since = np.zeros(pixels, np.int64)  # level change at or after F
    n = xs.shape[0]
    for i in range(n):
        pixel = np.int64(ys[i]) * width + np.int64(xs[i])
        if ts[i] >= horizon:
            if first_after[pixel] < 0:
                first_after[pixel] = i
            if ts[i] == ts[first_after[pixel]]:
                first_change[pixel] += cs[i]
            since[pixel] += cs[i]
        else:
            last_before[pixel] = i
    size = n + 2 * pixels
    out_pixel = np.empty(size, np.int64)
    out_t = np.empty(size, np.int64)
    out_change = np.empty(size, np.int64)
    k = np.int64(0)  # (not a literal 0: one compile of _in_time_order, not two)
    for pixel in range(pixels):  # the knot before F, carrying the whole level
        if not fired[pixel]:
            continue
        if first_after[pixel] < 0:  # no knot since F: its last knot
            out_pixel[k], out_t[k], out_change[k] = pixel, last_t[pixel], level[pixel]
            k += 1
            continue
        t1 = ts[first_after[pixel]]
        before = level[pixel] - since[pixel]
        y, x = pixel // width, pixel % width
        if first_change[pixel] == 0 and t1 < t_last:
            # Flat into it for good (a held knot, events that cancel; at the last time,
            # events of the next chunk may still make a ramp of it).
            out_pixel[k], out_t[k] = pixel, region_t[row[y] * out_w + column[x]]
            out_change[k] = before
            k += 1
        elif last_before[pixel] >= 0 and ts[last_before[pixel]] >= t1 - delay:
            out_pixel[k], out_t[k], out_change[k] = pixel, ts[last_before[pixel]], before
            k += 1
        elif t1 - delay < horizon:  # the held knot (or the front knot at t_start)
            out_pixel[k], out_t[k] = pixel, max(t1 - delay, t_start)
            out_change[k] = before
            k += 1
        else:  # flat from its last knot to t1 - D: at its region's last breakpoint
            out_pixel[k], out_t[k] = pixel, region_t[row[y] * out_w + column[x]]
            out_change[k] = before
            out_pixel[k + 1], out_t[k + 1], out_change[k + 1] = pixel, t1 - delay, 0
            k += 2
    by_pixel = k  # the first part's end
    previous = np.full(pixels, -1, np.int64)  # place of each pixel's last knot since F
    for i in range(n):  # the knots since F
        if ts[i] < horizon:
            continue
        pixel = np.int64(ys[i]) * width + np.int64(xs[i])
        c = cs[i]
        at = previous[pixel]
        if at >= 0 and out_t[at] == ts[i]:
            out_change[at] += c
            continue
        # (No held knot between two knots since F: they are at most D apart, the last
        # input time being at most F + D.)
        out_pixel[k], out_t[k], out_change[k] = pixel, ts[i], c
        previous[pixel] = k
        k += 1
    return _in_time_order(out_pixel[:k], out_t[:k], out_change[:k], by_pixel, width)


@compiled_loop
def _seed(
    kp: np.ndarray, kt: np.ndarray, kc: np.ndarray, width: int, column: np.ndarray,
    row: np.ndarray, out_w: int, delay: int, t_start: int, horizon: int, pixel_t: np.ndarray,
    one: int, slopes: np.ndarray, deltas: np.ndarray, pixels: np.ndarray, e_t: np.ndarray,
    e_region: np.ndarray, e_slope: np.ndarray, e_jump: np.ndarray, e_active: np.ndarray,
    e_delta: np.ndarray, s_t: np.ndarray, s_region: np.ndarray, s_slope: np.ndarray,
    s_delta: np.ndarray, value: np.ndarray, slope_sum: np.ndarray, since: np.ndarray,
    active: np.ndarray, error: np.ndarray, error_slope: np.ndarray,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """A ramps' session from a state's knots ``(pixel, t, change)`` (time order).

    Fills the pixels' table, the rings (from their start) and each region's value,
    slope, active ramps and error at its last breakpoint before ``F`` (``since``, which
    holds ``t_start`` for a region without one). Every knot at or after ``F`` gets an end
    in the ring (a held knot's with no change of its own), so each ramp that starts
    there is added to it. Returns the rings' tails.

    Raises:
        ValueError: for two knots of a pixel more than ``D`` apart (not a state of this
            ``max_delay``).
    """
    n = kp.shape[0]
    for i in range(n):  # each region's last breakpoint before F
        if kt[i] < horizon:
            pixel = kp[i]
            r = row[pixel // width] * out_w + column[pixel % width]
            since[r] = max(since[r], kt[i])
    mask = e_t.shape[0] - 1
    last = np.full(pixel_t.shape[0], -1, np.int64)  # each pixel's last knot so far
    prior = np.full(pixel_t.shape[0], -1, np.int64)  # and the one before it
    entry = np.full(n, -1, np.int64)  # each knot's end in the ring (-1: before F)
    ends, starts = 0, 0
    for i in range(n):
        pixel, t, c = kp[i], kt[i], kc[i]
        r = row[pixel // width] * out_w + column[pixel % width]
        before = last[pixel]
        last[pixel], prior[pixel] = i, before
        pixels[pixel, 4] += c  # the first knot carries the whole level
        if t < horizon:  # its ramp ended by the region's breakpoint
            value[r] += c * one
            continue
        k = ends & mask
        e_t[k], e_region[k] = t, r
        e_slope[k], e_jump[k], e_active[k], e_delta[k] = 0, 0, 0, 0.0
        entry[i] = ends
        ends += 1
        if c == 0:  # a held knot (or events that cancel): flat before it
            continue
        # From the pixel's previous knot, else from the front knot.
        h = kt[before] if before >= 0 else max(t_start, t - delay)
        length = t - h
        if length > delay:
            raise ValueError("two knots of a pixel are more than max_delay apart")
        slope, delta, count = c * slopes[length], c * deltas[length], abs(c)
        e_slope[k] -= slope
        e_jump[k] += c * one - slope * length
        e_delta[k] -= delta
        if length == 0:
            continue  # a jump (at t_start)
        e_active[k] -= count
        if h < horizon:  # started before F: active at the region's breakpoint
            value[r] += slope * (since[r] - h)
            error[r] += delta * (since[r] - h)
            slope_sum[r] += slope
            error_slope[r] += delta
            active[r] += count
        elif before >= 0:  # at the pixel's previous knot's end
            j = entry[before] & mask
            e_slope[j] += slope
            e_delta[j] += delta
            e_active[j] += count
        else:  # at t_start, the horizon (a stream shorter than D): an entry a ramp, as the
            # knot's |c| events would have made them (the sweep counts an entry as one ramp)
            unit = 1 if c > 0 else -1
            for _ in range(count):
                j = starts & mask
                s_t[j], s_region[j] = h, r
                s_slope[j], s_delta[j] = unit * slopes[length], unit * deltas[length]
                starts += 1
    for pixel in range(pixel_t.shape[0]):
        i = last[pixel]
        if i < 0:
            continue
        pixels[pixel, 0] = pixel_t[pixel]
        pixels[pixel, 2] = max(entry[i], 0)  # >= 0: the pixel has a knot
        j = prior[pixel]
        pixels[pixel, 1] = kt[j] if j >= 0 else t_start
        pixels[pixel, 3] = entry[j] if j >= 0 else -1
    return ends, starts


def window_state(session: RampSession) -> WindowState:
    """The package's state of the stream a ramps' session has read (after a chunk).

    Args:
        session: a :class:`~.linear_ramps.RampSession` that has read at least one chunk.

    Returns:
        The :class:`WindowState` the package's ``estimation_step`` resumes from: the
        package's events after the ones the session returned, with the package's settings
        for the same sensor, factor, threshold and ``max_delay``.
    """
    settings, pixels = session.settings, session.pixels
    q_change, region_t = session.regions[8], session.regions[9]
    x, y, t, change = _knots(
        *session.recent, settings.width, settings.column,
        settings.row, settings.out_w, settings.delay, session.t_start, session.horizon,
        session.t_last, pixels[:, 0], pixels[:, 2] >= 0, pixels[:, 4], region_t)
    knots = Events(torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(t),
                   torch.from_numpy(change > 0))
    t_start = torch.tensor(session.t_start, dtype=torch.int64)
    # The crossings returned since each region's last change swept: the sweep moved q from
    # q_change to the horizon along one ramp (one way), less those held at the horizon.
    held = np.bincount(session.at_horizon[0], minlength=q_change.shape[0])
    returned = np.abs(session.regions[4] - q_change) - held
    return WindowState(
        t_start, torch.tensor(session.t_last, dtype=torch.int64), session.horizon, knots,
        torch.from_numpy(change), torch.from_numpy(pixels[:, 0].copy()),
        torch.from_numpy(q_change.copy()), torch.from_numpy(returned))


def ramp_session(state: WindowState, settings: RampSettings, max_events: int) -> RampSession:
    """A ramps' session that carries on from the package's state (after a chunk).

    Args:
        state: the package's :class:`WindowState` after at least one chunk, int64
            timestamps, of the same sensor, factor, threshold and ``max_delay`` as
            ``settings``.
        settings: the ramps' :class:`~.linear_ramps.RampSettings`.
        max_events: as for :class:`~.linear_ramps.RampSession` (its rings also hold the
            state's knots).

    Returns:
        A session whose chunks give the package's events after the ones returned so far:
        each region starts at its last breakpoint before the horizon with the state's
        reference index, and of the crossings it finds after it, the first ``returned`` are
        not returned again (by their count, as the windowed step drops them).

    Raises:
        ValueError: for a state that has read no chunk, or of other than int64 timestamps,
            or whose knots are more than ``max_delay`` apart (not a state of these settings).
    """
    if state.horizon is None:
        raise ValueError("the state has read no chunk yet")
    if state.t_last.dtype != torch.int64:
        raise ValueError(f"the ramps take int64 timestamps, got {state.t_last.dtype}")
    t_start, horizon = int(state.t_start), int(state.horizon)
    knots = state.knots
    session = RampSession(t_start, max_events + knots.num_events // 4 + 1, settings)
    pixel = (knots.y.to(torch.int64) * settings.width + knots.x).numpy()
    t, change = knots.t.numpy(), state.change.numpy()
    # An end for each knot from F on, and at most a start for each of their events.
    session.reserve(max(knots.num_events, int(np.abs(change[t >= horizon]).sum())))
    value, slope_sum, since, _, q, active, error, error_slope, q_change, t_change = (
        session.regions)
    session.tail_e, session.tail_s = _seed(
        pixel, t, change, settings.width, settings.column, settings.row, settings.out_w,
        settings.delay, t_start, horizon, state.pixel_t.numpy(), settings.one,
        settings.slopes, settings.deltas, session.pixels, *session.ends, *session.starts,
        value, slope_sum, since, active, error, error_slope)
    q[:] = q_change[:] = state.q.numpy()
    t_change[:] = since
    session.horizon, session.t_last = horizon, int(state.t_last)
    session.returned = (horizon, state.returned.numpy().copy())
    recent = np.searchsorted(t, horizon - settings.delay)
    session.recent = (pixel[recent:] % settings.width, pixel[recent:] // settings.width,
                      t[recent:].copy(), change[recent:].copy())
    return session
