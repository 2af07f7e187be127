"""LIF pooling (method 6) as a stream: consecutive chunks give exactly the batch spikes.

The batch kernel (:func:`.pooling.lif_pooling`) bins the stream
into steps of ``dt`` from ``t_start`` and turns a spike of step ``k`` into an event at
``t_start + (k + 1) * dt`` clipped to ``t_end``. A chunk ending at ``t`` (its last timestamp)
*decides* the spikes of a step ``k`` when

- the step is closed: it ends before the step of ``t`` begins, so no later event (all at
  ``t`` or after) can fall into it; the firing chains of neurons through empty steps up to
  ``k`` are then fixed too (they change only where input arrives);
- its time ``t_start + (k + 1) * dt`` is at most ``t``, so the clip to the stream's end,
  which is at least ``t``, cannot move it.

The decided steps are a prefix of the steps; a chunk returns the spikes of the steps it newly
decides, in the batch order (by step, then neuron). The state holds the stream's ``t_start``,
the neurons after the decided steps (:class:`.pooling.LIFState`:
each region's membranes at its last input, and that step, so the kernel continues through a
gap exactly as it does in one call) and the input of the undecided steps. The end of the stream
processes that input and the chains up to the last step, with times clipped to ``t_end``. The
kernel is the batch one (:func:`~evdown_torch.transforms.functional.lif.pooling.lif_spikes`), so the
cost still follows the events: a call touches the regions with input and the neurons that are
firing through empty steps.

Live chunks. The state keeps the steps of the pending input, so a chunk steps only its own
events (by searching the steps' first times where there are many events per step), and the
decided input goes to the kernel in two pieces, the pending events and the decided prefix of
the chunk, which it counts piece by piece without joining them (a live chunk's cells are few
next to its events: :func:`~evdown_torch.transforms.functional.lif.keys.counted_cells`); only
the rest of the chunk (the events of its last, open step) is copied, into the new pending
input.
"""

from __future__ import annotations

import math
from typing import NamedTuple, cast

import torch
from torch import Tensor

from evdown_torch._tensors import sort_by_time
from evdown_torch.checks import check_state_memory, output_size
from evdown_torch.events import Events
from evdown_torch.transforms.functional.lif.pooling import (
    LIFSettings,
    LIFState,
    initial_state,
    lif_spikes,
)
from evdown_torch.transforms.functional.lif.settings import LIFPoolingSettings
from evdown_torch.transforms.functional.lif.steps import (
    spikes_to_events,
    step_end_time,
    step_indices,
)

__all__ = [
    "LIFStreamState",
    "lif_finish",
    "lif_init",
    "lif_pooling_stream",
    "lif_pooling_stream_end",
    "lif_step",
]


class LIFStreamState(NamedTuple):
    """State of a LIF pooling stream between chunks.

    Attributes:
        t_start: ``()`` tensor, the stream's first timestamp (steps count from it).
        last_t: ``()`` tensor, the latest timestamp seen.
        neurons: the neurons after the decided steps.
        decided: the last step whose spikes were returned (-1: none yet).
        pending: the events of the steps after ``decided``, time-sorted.
        pending_steps: ``(len(pending),)`` int64 step of every pending event.
    """

    t_start: Tensor
    last_t: Tensor
    neurons: LIFState
    decided: int
    pending: Events
    pending_steps: Tensor


def _spike_time_within(step: int, *, t_start: Tensor, last_t: Tensor, dt: float) -> bool:
    """Whether ``t_start + (step + 1) * dt``, as the kernel computes it, is at most ``last_t``.

    The same arithmetic as :func:`~evdown_torch.transforms.functional.lif.pooling.step_end_time`
    before its clip (Python ints and IEEE doubles, as torch's int64 and float64).
    """
    if t_start.is_floating_point():
        return float(t_start) + float(step + 1) * dt <= float(last_t)
    span = int(last_t) - int(t_start)
    if dt.is_integer():
        return (step + 1) * int(dt) <= span
    return math.floor(float(step + 1) * dt + 0.5) <= span


def _last_decided_step(
    last_step: int, decided: int, *, t_start: Tensor, last_t: Tensor, dt: float
) -> int:
    """The last step a stream that has reached ``last_t`` (in step ``last_step``) decides.

    Steps before ``last_step`` are closed; of those, the ones whose time is at most ``last_t``
    (all of them but for rounding, so the search below rarely runs) are decided.
    """
    low, high = decided, last_step - 1  # low is decided; find the last decided in (low, high]
    if high <= low or _spike_time_within(high, t_start=t_start, last_t=last_t, dt=dt):
        return max(high, low)
    high -= 1
    while low < high:  # bisection on a monotone predicate: O(log) tests
        middle = (low + high + 1) // 2
        if _spike_time_within(middle, t_start=t_start, last_t=last_t, dt=dt):
            low = middle
        else:
            high = middle - 1
    return low


def _fresh_state(
    events: Events, sensor_size: tuple[int, int, int], factor: tuple[int, int]
) -> LIFStreamState:
    """A stream's state before its first chunk ``events`` (time-sorted).

    ``t_start`` is its first timestamp, every membrane at rest, no step decided, nothing
    pending.
    """
    wo, ho, _ = output_size(sensor_size, factor)
    check_state_memory("LIFPooling's session", sensor_size, factor, region_bytes=16,
                       device=events.device)  # two float32 membranes and an int64 step
    return LIFStreamState(
        events.t[0], events.t[0], initial_state(wo * ho, events.device), -1,
        Events.empty(events.t.dtype, events.device),
        torch.empty(0, dtype=torch.int64, device=events.device),
    )


def lif_pooling_stream(
    events: Events,
    state: LIFStreamState | None,
    settings: LIFSettings,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    time_sorted: bool = False,
) -> tuple[Events, LIFStreamState | None]:
    """One chunk of a LIF pooling stream: the spikes it decides, and the new state.

    Args:
        events: the chunk, no earlier than the previous chunks' last event.
        state: the state after the previous chunks, ``None`` for the first.
        settings: the neuron's settings (``dt`` in the unit of ``t``).
        sensor_size: input sensor ``(W, H, P)``.
        factor: ``(fx, fy)``, positive integers.
        time_sorted: the chunk is known to be in time order (a session's, which sorts it
            first), so its order is not checked again.

    Returns:
        ``(output, state)``: the events of the newly decided steps (sorted by ``t``; the
        concatenation over the chunks and :func:`lif_pooling_stream_end` is the batch output),
        and the new state (``state`` itself for an empty chunk).

    Raises:
        ValueError: when the stream's steps cannot be indexed in int64, or the output exceeds
            limit in force (:func:`evdown_torch.max_output_events`, per chunk); ``state`` is
            not modified.

    Example:
        >>> ev = Events.from_columns([0, 1, 0, 1, 3], [0, 0, 1, 1, 0], [0, 1, 2, 3, 9],
        ...                          [1, 1, 1, 1, 0])
        >>> settings = LIFSettings(dt=2, beta=1.0, threshold=1.0, weight=0.3)
        >>> grid = dict(sensor_size=(4, 2, 2), factor=(2, 2))
        >>> out, state = lif_pooling_stream(ev.select(torch.arange(4)), None, settings, **grid)
        >>> out.t.tolist()  # step 1 ([2, 4)) is still open at t = 3
        []
        >>> out, state = lif_pooling_stream(ev.select(torch.tensor([4])), state, settings, **grid)
        >>> out.t.tolist(), state.decided
        ([4], 3)
    """
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device), state
    if not time_sorted:
        events = sort_by_time(events)
    if state is None:
        state = _fresh_state(events, sensor_size, factor)
    # The steps of the new events only (the pending ones' are kept: the same, see
    # step_indices, whose dt changes only while every event is in step 0).
    steps, last_step, end_dt = step_indices(events.t, settings.dt, t_start=state.t_start)
    last_t = events.t[-1]
    decided = _last_decided_step(
        last_step, state.decided, t_start=state.t_start, last_t=last_t, dt=settings.dt
    )
    if decided == state.decided:
        return Events.empty(events.t.dtype, events.device), state._replace(
            last_t=last_t, pending=Events.cat([state.pending, events]),
            pending_steps=torch.cat([state.pending_steps, steps]),
        )
    # The events of decided steps: a prefix of the pending ones (usually all), then a prefix
    # of the new ones (none unless every pending one is decided), passed as two pieces.
    k = int(torch.searchsorted(state.pending_steps, decided, right=True))
    n = int(torch.searchsorted(steps, decided, right=True))
    spike_step, neuron, neurons = lif_spikes(
        [state.pending.part(0, k), events.part(0, n)],
        [state.pending_steps[:k], steps[:n]], settings,
        state=state.neurons, last_step=decided, from_step=state.decided + 1,
        sensor_size=sensor_size, factor=factor,
    )
    t = step_end_time(spike_step, t_start=state.t_start, t_end=last_t, dt=end_dt)
    out = spikes_to_events(spike_step, neuron, t, sensor_size=sensor_size, factor=factor)
    rest = Events.cat([state.pending.part(k), events.part(n)])
    rest_steps = torch.cat([state.pending_steps[k:], steps[n:]])
    neurons = cast(LIFState, neurons)  # kept: lif_spikes returns the state (keep_state)
    return out, LIFStreamState(state.t_start, last_t, neurons, decided, rest, rest_steps)


def lif_pooling_stream_end(
    state: LIFStreamState | None,
    settings: LIFSettings,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
) -> Events | None:
    """The end of a LIF pooling stream: the spikes of the steps no chunk decided.

    The pending input is processed and the neurons' firing chains run up to the step of
    ``t_end`` (the stream's last timestamp); times are clipped to ``t_end``, as in the batch.

    Args:
        state: the state after the last chunk (``None``: no event, returns ``None``).
        settings: the neuron's settings, as for every chunk.
        sensor_size: input sensor ``(W, H, P)``.
        factor: ``(fx, fy)``, positive integers.

    Returns:
        The remaining events, sorted by ``t``, or ``None`` when no event was streamed.
    """
    if state is None:
        return None
    pending = state.pending
    times = torch.cat([pending.t, state.last_t.reshape(1)])
    steps, last_step, end_dt = step_indices(times, settings.dt, t_start=state.t_start)
    spike_step, neuron, _ = lif_spikes(
        pending, steps[:-1], settings, state=state.neurons, last_step=last_step,
        from_step=state.decided + 1, sensor_size=sensor_size, factor=factor, keep_state=False,
    )
    t = step_end_time(spike_step, t_start=state.t_start, t_end=state.last_t, dt=end_dt)
    return spikes_to_events(spike_step, neuron, t, sensor_size=sensor_size, factor=factor)


def lif_init(settings: LIFPoolingSettings, events: Events) -> LIFStreamState:
    """LIF pooling's ``init_state``: a stream whose first (time-sorted) chunk is ``events``."""
    return _fresh_state(events, settings.sensor_size, settings.factor)


def lif_step(
    events: Events, state: LIFStreamState, settings: LIFPoolingSettings
) -> tuple[Events, LIFStreamState]:
    """LIF pooling's ``step``: :func:`lif_pooling_stream` on one (time-sorted) chunk."""
    out, new = lif_pooling_stream(events, state, settings.neuron,
                                  sensor_size=settings.sensor_size, factor=settings.factor,
                                  time_sorted=True)
    return out, new if new is not None else state


def lif_finish(state: LIFStreamState, settings: LIFPoolingSettings) -> Events | None:
    """LIF pooling's ``finish``: :func:`lif_pooling_stream_end`."""
    return lif_pooling_stream_end(state, settings.neuron, sensor_size=settings.sensor_size,
                                  factor=settings.factor)
