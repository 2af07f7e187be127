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

from evdown_torch.checks import check_state_memory, output_size
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events
from evdown_torch.transforms.functional.batch import Stacked, run_stacked
from evdown_torch.transforms.functional.lif.pooling import (
    LIFState,
    initial_state,
    lif_pooling,
    lif_spikes,
)
from evdown_torch.transforms.functional.lif.settings import LIFPoolingSettings
from evdown_torch.transforms.functional.lif.steps import (
    StepRuns,
    Steps,
    each_step,
    spikes_to_events,
    step_end_time,
    step_indices,
    step_runs,
)
from evdown_torch.transforms.functional.protocol import Method

__all__ = [
    "LIF_POOLING",
    "LIFStreamState",
    "lif_pooling_finish",
    "lif_pooling_init",
    "lif_pooling_stacked",
    "lif_pooling_step",
    "lif_pooling_whole",
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

    The same arithmetic as :func:`~evdown_torch.transforms.functional.lif.steps.step_end_time`
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


def lif_pooling_init(settings: LIFPoolingSettings, events: Events) -> LIFStreamState:
    """LIF pooling's ``init_state``: a stream whose first (time-sorted) chunk is ``events``."""
    return _fresh_state(events, settings.sensor_size, settings.factor)


def lif_pooling_step(
    events: Events, state: LIFStreamState, settings: LIFPoolingSettings
) -> tuple[Events, LIFStreamState]:
    """LIF pooling's ``step``: the spikes one time-sorted chunk decides, and the new state.

    Args:
        events: the chunk (non-empty, time-sorted), no earlier than the previous chunks'
            last event.
        state: the state after the previous chunks (:func:`lif_pooling_init` for the first).
        settings: the region geometry and the neuron's settings (``dt`` in the unit of ``t``).

    Returns:
        ``(output, state)``: the events of the newly decided steps (sorted by ``t``; the
        concatenation over the chunks and :func:`lif_pooling_finish` is the batch output),
        and the new state.

    Raises:
        ValueError: when the stream's steps cannot be indexed in int64, or the output exceeds
            limit in force (:func:`evdown_torch.max_output_events`, per chunk); ``state`` is
            not modified.

    Example:
        >>> ev = Events.from_columns([0, 1, 0, 1, 3], [0, 0, 1, 1, 0], [0, 1, 2, 3, 9],
        ...                          [1, 1, 1, 1, 0])
        >>> from evdown_torch.transforms.functional.lif.settings import LIFSettings
        >>> neuron = LIFSettings(dt=2, beta=1.0, threshold=1.0, weight=0.3)
        >>> settings = LIFPoolingSettings((4, 2, 2), (2, 2), neuron)
        >>> first = ev.select(torch.arange(4))
        >>> out, state = lif_pooling_step(first, lif_pooling_init(settings, first), settings)
        >>> out.t.tolist()  # step 1 ([2, 4)) is still open at t = 3
        []
        >>> out, state = lif_pooling_step(ev.select(torch.tensor([4])), state, settings)
        >>> out.t.tolist(), state.decided
        ([4], 3)
    """
    cell, sensor_size, factor = settings.neuron, settings.sensor_size, settings.factor
    # The steps of the new events only (the pending ones' are kept: the same, see
    # step_indices, whose dt changes only while every event is in step 0), as runs where
    # found by searching (a live chunk's: only the pending rest is stepped event by event).
    steps, last_step, end_dt = step_runs(events.t, cell.dt, t_start=state.t_start)
    last_t = events.t[-1]
    decided = _last_decided_step(
        last_step, state.decided, t_start=state.t_start, last_t=last_t, dt=cell.dt
    )
    if decided == state.decided:
        return Events.empty(events.t.dtype, events.device), state._replace(
            last_t=last_t, pending=Events.cat([state.pending, events]),
            pending_steps=torch.cat([state.pending_steps, each_step(steps)]),
        )
    # The events of decided steps: a prefix of the pending ones (usually all), then a prefix
    # of the new ones (none unless every pending one is decided), passed as two pieces.
    k = int(torch.searchsorted(state.pending_steps, decided, right=True))
    decided_steps: Steps
    rest_of_steps: Steps
    if isinstance(steps, StepRuns):
        decided_steps, rest_of_steps = steps.split(decided + 1)
        n = decided_steps.num_events
    else:
        n = int(torch.searchsorted(steps, decided, right=True))
        decided_steps, rest_of_steps = steps[:n], steps[n:]
    spike_step, neuron, neurons = lif_spikes(
        [state.pending.part(0, k), events.part(0, n)],
        [state.pending_steps[:k], decided_steps], cell,
        state=state.neurons, last_step=decided, from_step=state.decided + 1,
        sensor_size=sensor_size, factor=factor,
    )
    t = step_end_time(spike_step, t_start=state.t_start, t_end=last_t, dt=end_dt)
    out = spikes_to_events(spike_step, neuron, t, sensor_size=sensor_size, factor=factor)
    rest = Events.cat([state.pending.part(k), events.part(n)])
    rest_steps = torch.cat([state.pending_steps[k:], each_step(rest_of_steps)])
    neurons = cast(LIFState, neurons)  # kept: lif_spikes returns the state (keep_state)
    return out, LIFStreamState(state.t_start, last_t, neurons, decided, rest, rest_steps)



def lif_pooling_finish(state: LIFStreamState, settings: LIFPoolingSettings) -> Events | None:
    """LIF pooling's ``finish``: the spikes of the steps no chunk decided.

    The pending input is processed and the neurons' firing chains run up to the step of
    ``t_end`` (the stream's last timestamp); times are clipped to ``t_end``, as in the batch.

    Returns:
        The remaining events, sorted by ``t``.
    """
    cell, sensor_size, factor = settings.neuron, settings.sensor_size, settings.factor
    pending = state.pending
    times = torch.cat([pending.t, state.last_t.reshape(1)])
    steps, last_step, end_dt = step_indices(times, cell.dt, t_start=state.t_start)
    spike_step, neuron, _ = lif_spikes(
        pending, steps[:-1], cell, state=state.neurons, last_step=last_step,
        from_step=state.decided + 1, sensor_size=sensor_size, factor=factor, keep_state=False,
    )
    t = step_end_time(spike_step, t_start=state.t_start, t_end=state.last_t, dt=end_dt)
    return spikes_to_events(spike_step, neuron, t, sensor_size=sensor_size, factor=factor)


def lif_pooling_whole(events: Events, settings: LIFPoolingSettings) -> Events:
    """The whole stream in one call: :func:`.pooling.lif_pooling`."""
    return lif_pooling(events, settings.neuron, sensor_size=settings.sensor_size,
                       factor=settings.factor)


def lif_pooling_stacked(batch: EventBatch, settings: LIFPoolingSettings) -> EventBatch:
    """The whole-stream kernel once on the stacked batch.

    Each recording is binned from its own ``t_start`` and ends at its own ``t_end``.
    """

    def kernel(stacked: Stacked) -> Events:
        return lif_pooling(stacked.events, settings.neuron, sensor_size=settings.sensor_size,
                           factor=settings.factor, recording_spans=(stacked.starts, stacked.ends))

    return run_stacked(batch, kernel, sensor_size=settings.sensor_size, factor=settings.factor)


#: LIFPooling's kernels (:class:`~evdown_torch.LIFPooling`).
LIF_POOLING: Method[LIFPoolingSettings, LIFStreamState] = Method(
    lif_pooling_init, lif_pooling_step, lif_pooling_finish,
    whole=lif_pooling_whole, stacked=lif_pooling_stacked,
)
