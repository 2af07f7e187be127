"""Bounded-state streaming of the linear and cubic estimators (a finite ``max_delay``).

docs/semantics.md, "Bounded delay": with a delay ``D``, output earlier than
``tau - lag * D`` (``lag`` 1 for the linear method, 2 for the cubic one) is decided by the
input up to ``tau``. A session step therefore solves a *window* of the stream, with the one
driver of the batch kernels
(:func:`.driver.estimate_window`), and keeps only what the
future needs (:class:`WindowState`):

* the stream's ``t_start`` (the front knots) and last timestamp;
* the *horizon* ``F``: every output event earlier than it has been returned;
* the knot events the curves after ``F`` still need: of each pixel that has fired, its last
  knot earlier than ``F`` (the last two for the cubic method: PCHIP slopes look one knot
  back), with its whole level as its change, and all its knots since (held knots included);
* each output region's reference index after its last breakpoint earlier than ``F``, and
  how many of its crossings since have been returned (the next window drops as many of them
  by their order: :func:`~.solver.resumed_crossings`);
* each pixel's last knot time (where the next chunk's held knots start from).

Its size follows the sensor's active pixels and the last ``lag * D`` of input, not the
stream's length. Only the regions with a knot at or after ``F`` are solved: the others hold
their level until their next event, whose held knot comes after the next horizon.

The state's knot events are kept in stable time order, so a window is a merge of sorted
parts (:func:`.delay.merge_by_time`: the state's, the chunk's held knots, the chunk's
events) rather than a sort, and the next state takes from the window only each pixel's last
knots before the new horizon (:func:`_recent`), without grouping the whole window by pixel.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple, cast

import torch
from torch import Tensor

from evdown_torch._regions import region_of, region_xy
from evdown_torch._tensors import (
    changes,
    differences,
    ends,
    run_index,
    segmented_cumsum,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.checks import check_state_memory, output_size
from evdown_torch.events import Events, polarity_sign
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.estimation import delay
from evdown_torch.transforms.functional.estimation.delay import (
    effective_delay,
    held_knots,
    merge_by_time,
)
from evdown_torch.transforms.functional.estimation.driver import compiled_upkeep, estimate_window
from evdown_torch.transforms.functional.estimation.knots import (
    check_span,
)
from evdown_torch.transforms.functional.estimation.settings import EstimationSettings
from evdown_torch.transforms.functional.estimation.solver import Resume
from evdown_torch.transforms.functional.estimation.window_state import WindowState

__all__ = ["WindowState", "estimation_finish", "estimation_init", "estimation_step"]


def _regions(events: Events, factor: tuple[int, int], out_width: int) -> Tensor:
    rx, ry = region_of(events, factor)
    return ry * out_width + rx


def _trim(
    events: Events, change: Tensor, *, before: Tensor, keep: int, width: int
) -> tuple[Events, Tensor]:
    """One event per knot, dropping each pixel's knots earlier than ``before`` but ``keep``.

    The first knot kept of a pixel carries the pixel's whole level as its change.
    """
    pixel = events.y * width + events.x
    pixel, order = stable_sort_small(pixel)  # pixel order, time order inside a pixel
    t, change = take(events.t, order), take(change, order)
    new_pixel = changes(pixel)
    level = segmented_cumsum(change, where_true(new_pixel), run_index(new_pixel))
    at = where_true(ends(new_pixel | changes(t)))  # last event of each (pixel, t): a knot
    pixel, t, level = take(pixel, at), take(t, at), take(level, at)
    first = changes(pixel)
    rank = run_index(first)
    position = torch.arange(pixel.shape[0], device=pixel.device)
    position -= take(where_true(first), rank)
    done = t < before  # a prefix of each pixel's knots
    n_done = torch.zeros(int(rank[-1]) + 1, dtype=torch.int64, device=pixel.device)
    n_done.index_add_(0, rank, done.to(torch.int64))
    kept = where_true(~done | (position >= take(n_done, rank) - keep))
    pixel, t, level = take(pixel, kept), take(t, kept), take(level, kept)
    change = differences(level, where_true(changes(pixel)))
    x, y = region_xy(pixel, width)
    return Events(x, y, t, change > 0), change


def _recent(
    window: Events, change: Tensor, *, before: Tensor, keep: int, pixels: int, width: int,
    t_start: Tensor,
) -> tuple[Events, Tensor]:
    """The knot events of a time-sorted window that :func:`_trim` keeps, and fewer others.

    Of the events earlier than ``before``, each pixel's last ``keep`` knots are passed on and
    the events before them folded into one event at the earliest of those knots, carrying
    their level changes: the same knots at the same levels, so :func:`_trim` gives the same result
    as on the whole window, without grouping the whole window by pixel. ``t_start`` is the
    stream's first timestamp (no event is earlier).
    """
    cut = int(torch.searchsorted(window.t, before))
    if cut == 0 or window.num_events < delay.SMALL_WINDOW:  # nothing to spare
        return window, change
    t, head_change = window.t[:cut], change[:cut]
    pixel = window.y[:cut] * width + window.x[:cut]
    # Each pixel's keep-th last knot time before the cut; t_start with fewer knots, which
    # folds nothing (no event is earlier).
    since = torch.full((pixels,), t_start.item(), dtype=t.dtype, device=t.device)
    since.scatter_reduce_(0, pixel, t, "amax")
    for _ in range(keep - 1):
        earlier = torch.where(t < take(since, pixel), t, t_start)
        since = torch.full_like(since, t_start.item()).scatter_reduce_(0, pixel, earlier, "amax")
    fold = t < take(since, pixel)
    folded = torch.zeros(pixels, dtype=torch.int64, device=t.device)
    folded.index_add_(0, pixel, fold.to(torch.int64))
    carried = torch.zeros(pixels, dtype=torch.int64, device=t.device)
    carried.index_add_(0, pixel, head_change.masked_fill(~fold, 0))
    at = where_true(folded > 0)
    x, y = region_xy(at, width)
    carry = Events(x, y, take(since, at), torch.zeros_like(at, dtype=torch.bool))
    passed = where_true(~fold)
    tail = window.part(cut)
    events = Events.cat([carry, window.select(passed), tail])
    return events, torch.cat([take(carried, at), take(head_change, passed), change[cut:]])


def next_knots(
    window: Events, change: Tensor, *, before: Tensor, keep: int, width: int, pixels: int,
    t_start: Tensor,
) -> tuple[Events, Tensor]:
    """The knot events of the next state, kept of a time-sorted window, in stable time order.

    Each pixel's knots at or after ``before`` and its last ``keep`` before it, the first kept
    carrying the pixel's whole level (:func:`_trim`, after :func:`_recent` prunes what it
    would drop); ``width``: the sensor's ``W``; ``pixels``: its ``W * H``; ``t_start``: the
    stream's first timestamp.
    """
    recent, recent_change = _recent(window, change, before=before, keep=keep, pixels=pixels,
                                    width=width, t_start=t_start)
    kept, kept_change = _trim(recent, recent_change, before=before, keep=keep, width=width)
    by_time = torch.sort(kept.t, stable=True).indices
    return kept.select(by_time), take(kept_change, by_time)


class _Upkeep(NamedTuple):
    """The window's upkeep of a session step: the eager functions, or their compiled twins.

    ``next_knots`` takes ``(window, change, *, before, keep, width)``.
    """

    held_knots: Callable[..., Events]
    merge_by_time: Callable[[list[tuple[Events, Tensor]]], tuple[Events, Tensor]]
    next_knots: Callable[..., tuple[Events, Tensor]]


def _upkeep(t: Tensor, *, pixels: int, t_start: Tensor) -> _Upkeep:
    """The upkeep a step with timestamps ``t`` takes: compiled or eager.

    Compiled where :func:`~.driver.compiled_upkeep` says so (the same tensors), else eager,
    with the sensor's ``pixels`` and the stream's ``t_start`` that the eager
    :func:`next_knots` reads.
    """
    compiled = compiled_upkeep(t)
    if compiled is not None:
        return _Upkeep(compiled.held_knots, compiled.merge_by_time, compiled.next_knots)
    return _Upkeep(held_knots, merge_by_time,
                   functools.partial(next_knots, pixels=pixels, t_start=t_start))


def estimation_init(settings: EstimationSettings, events: Events) -> WindowState:
    """The estimators' ``init_state`` (bounded delay).

    Before the first (time-sorted) chunk ``events``: no knot yet, every pixel's last knot at
    ``t_start``, every region at reference index 0.
    """
    device, t_dtype = events.t.device, events.t.dtype
    width, height, _ = settings.sensor_size
    out_w, out_h, _ = settings.output_sensor_size
    check_state_memory("an estimator's session", settings.sensor_size, settings.factor,
                       pixel_bytes=events.t.element_size(), region_bytes=8, device=device)
    t_start = events.t[0]
    return WindowState(
        t_start, t_start, None, Events.empty(t_dtype, device),
        torch.zeros(0, dtype=torch.int64, device=device),
        torch.full((width * height,), t_start.item(), dtype=t_dtype, device=device),
        torch.zeros(out_w * out_h, dtype=torch.int64, device=device),
        torch.zeros(out_w * out_h, dtype=torch.int64, device=device),
    )


def estimation_step(
    events: Events, state: WindowState | None, settings: EstimationSettings
) -> tuple[Events, WindowState]:
    """One chunk of a bounded-delay stream: the outputs decided so far, and the new state.

    The outputs are the events earlier than ``tau - lag * D`` not returned yet (``tau``: the
    chunk's last timestamp).

    Args:
        events: ``N >= 1`` events in stable time order, none earlier than the previous
            chunk's last.
        state: the state after the previous chunk, ``None`` for the first.
        settings: the estimator's settings, ``max_delay`` set (a whole number for int64
            ``t``).

    Returns:
        ``(output, state)``: output sorted by ``t``, ``t`` of the input's dtype.

    Example:
        Two pixels of one region (threshold 0.25); pixel (1, 0) holds 0 until ``10 - D``:

        >>> settings = EstimationSettings((2, 1, 2), (2, 1), 0.25, max_delay=3, curve="linear")
        >>> ev = Events.from_columns([0, 1], [0, 0], [0, 10], [1, 1])
        >>> out, state = estimation_step(ev, None, settings)
        >>> out.t.tolist(), state.horizon  # decided: before 10 - 3
        ([0, 0], 7)
        >>> estimation_finish(state, settings).t.tolist()  # the ramp on [7, 10]
        [9, 10]
    """
    sensor_size, factor, max_delay = settings.sensor_size, settings.factor, settings.max_delay
    if max_delay is None:
        raise ValueError("a bounded-delay stream needs the settings' max_delay, got None")
    device, t_dtype = events.t.device, events.t.dtype
    width = sensor_size[0]
    out_w, out_h, _ = output_size(sensor_size, factor)
    if state is None:
        state = estimation_init(settings, events)
    tau = events.t[-1]
    check_span(state.t_start, tau)  # before any time arithmetic
    if use_compiled(events.t):  # (the module imports Numba)
        from evdown_torch.transforms.functional.compiled.linear_stream import ramps_step

        stepped = ramps_step(events, state, settings)
        if stepped is not None:  # else a chunk the ramps do not take: the window's
            return stepped
    upkeep = _upkeep(events.t, pixels=state.pixel_t.shape[0], t_start=state.t_start)
    pixel = events.y * width + events.x
    held = upkeep.held_knots(events, max_delay=max_delay, t_start=take(state.pixel_t, pixel))
    pixel_t = state.pixel_t.clone()
    pixel_t.scatter_reduce_(0, pixel, events.t, "amax")
    # Nothing is earlier than t_start: a horizon before it (a delay longer than the stream so
    # far, up to 1e300) decides nothing, and held as t_start it stays an int64 / float time.
    horizon = max(tau.item() - settings.lag * effective_delay(max_delay, events.t),
                  state.t_start.item())
    if state.horizon is not None:
        horizon = max(horizon, state.horizon)
    cut = None if state.horizon is None else torch.tensor(state.horizon, dtype=t_dtype,
                                                          device=device)

    # The window: every knot event of the regions with something undecided, in stable time
    # order (the state's, then the held knots, then the chunk's events; each part is sorted).
    touched = torch.zeros(out_w * out_h, dtype=torch.bool, device=device)
    touched[_regions(events, factor, out_w)] = True  # a held knot's pixel has an event here
    old_region = _regions(state.knots, factor, out_w)
    if cut is not None:
        touched[take(old_region, where_true(state.knots.t >= cut))] = True
    in_window = take(touched, old_region)
    old = where_true(in_window)
    window, window_change = upkeep.merge_by_time([
        (state.knots.select(old), take(state.change, old)),
        (held, torch.zeros(held.num_events, dtype=torch.int64, device=device)),
        (events, polarity_sign(events.p, torch.int64)),
    ])

    next_cut = torch.tensor(horizon, dtype=t_dtype, device=device)
    out, after = estimate_window(
        window, change=window_change, t_start=state.t_start, t_end=tau, settings=settings,
        resume=Resume(cut, state.q, state.returned), next_cut=next_cut,
    )
    kept, kept_change = upkeep.next_knots(window, window_change, before=next_cut,
                                          keep=settings.lag, width=width)
    outside = where_true(~in_window)
    knots, change = upkeep.merge_by_time([
        (state.knots.select(outside), take(state.change, outside)), (kept, kept_change)])
    after = cast(Resume, after)  # estimate_window returns it with a resume and a next cut
    new_state = WindowState(state.t_start, tau, horizon, knots, change, pixel_t, after.q,
                            after.returned)
    return out, new_state


def estimation_finish(state: WindowState, settings: EstimationSettings) -> Events | None:
    """The output from the horizon to the end of the stream (its last timestamp).

    Returns:
        The remaining output events sorted by ``t``, or ``None`` when there are none.
    """
    factor = settings.factor
    out_w = settings.output_sensor_size[0]
    cut = torch.tensor(state.horizon, dtype=state.t_last.dtype, device=state.t_last.device)
    region = _regions(state.knots, factor, out_w)
    touched = torch.zeros_like(state.q, dtype=torch.bool)
    touched[take(region, where_true(state.knots.t >= cut))] = True
    in_window = where_true(take(touched, region))
    if in_window.shape[0] == 0:
        return None
    out, _ = estimate_window(
        state.knots.select(in_window), change=take(state.change, in_window),
        t_start=state.t_start, t_end=state.t_last, settings=settings,
        resume=Resume(cut, state.q, state.returned),
    )
    return out
