"""LIF pooling kernel (method 6), event-driven: a neuron is touched only when input reaches it.

The stream is binned into steps of ``dt`` from ``t_start``; one ``snntorch.Leaky`` neuron per
output region and polarity integrates the pooled events of each step. Stepping every neuron
through every step costs ``T x Ho x Wo``; this kernel computes the same spikes with a cost
that follows the events:

- **Cells.** The events are grouped into *cells*, the ``(region, step)`` pairs that hold
  events; a cell's input current for the region's two neurons is the pooled count of its
  events (``w * S - w_inh * S'``, as :class:`~evdown_torch.models.SpikingPooling` computes it).
  Steps without input are never visited. Where the cells are few next to the events (a live
  chunk) every cell's events are counted in one pass
  (:mod:`~evdown_torch.transforms.functional.lif.keys`); otherwise they are grouped.
- **Gaps in closed form.** Between two cells of a region the input is zero. A membrane at or
  below threshold only decays, by ``beta ** g`` over ``g`` steps. A membrane above threshold
  keeps firing (snntorch applies the reset one step later): with reset ``"subtract"`` the
  chain ``U_j = beta * U_{j-1} - theta`` falls below threshold after a number of spikes solved
  from ``beta ** j * (U + A) - A > theta``, ``A = theta / (1 - beta)`` (``U - j * theta`` for
  ``beta = 1``); with ``"none"`` ``beta ** j * U > theta`` gives the count (every step for
  ``beta = 1``); with ``"zero"`` the neuron is silent after its reset. The first
  :data:`EXACT_CHAIN_STEPS` steps of a chain use the float32 arithmetic of stepping (chains
  are usually shorter); a longer chain continues in closed form, its count solved in float64
  and checked against the chain's value on both sides. No loop runs over the steps of a gap.
- **Rounds.** Cells are processed by their rank within their region: round ``r`` updates the
  ``r``-th cell of every region that has one, all at once (regions are laid out by decreasing
  number of cells, so the regions of a round are a prefix and every update is a slice). The
  element work is proportional to the cells; the number of rounds (a fixed cost of a few
  tensor operations each) is the largest number of cells of one region, at most the number
  of steps that hold events (:mod:`~evdown_torch.transforms.functional.lif.rounds`). On
  the CPU compiled loops take the cells as they come instead, region by region, with the same
  float32 arithmetic, and do the counting, merging and ordering around them too
  (:mod:`~evdown_torch.transforms.functional.compiled.lif`,
  :mod:`~evdown_torch.transforms.functional.compiled.lif_cells`).
- **Small calls in closed form.** A call that needs no state back (a recording alone or a
  small batch) and whose cells fit a small table takes
  :mod:`~evdown_torch.transforms.functional.lif.closed_form` instead: the membranes between
  firings as cumulative sums, the firings by binary search (one pass per firing of the
  busiest neuron, not per active step), every decision certified against a bound on the
  rounds' float32 rounding; where one is not certain the rounds compute the call, so the
  spikes are the same either way.

State. The core, :func:`lif_spikes`, can start from a :class:`LIFState` (each region's
membranes at its last input, and that step: a state cell in front of the region's cells), run
up to a given last step and return the spikes from a given step on; the streaming session
(:mod:`evdown_torch.transforms.functional.lif.stream`) continues the neurons chunk by chunk
with it, computing every gap exactly as one call does.

Exactness. The update at a cell is snntorch's float32 arithmetic, in its order, so runs of
consecutive active steps, and gaps of one step, are bit-identical to the module. Over a longer
gap the decay ``beta ** g`` is one float32 power (the exact power rounded once, whatever
the cell's place among the call's cells: :mod:`~evdown_torch.transforms.functional.lif.powers`)
where stepping rounds ``g`` products (identical when ``beta`` is 0, 1 or a power of two), and
a chain longer than
:data:`~evdown_torch.transforms.functional.lif.chains.EXACT_CHAIN_STEPS` is one float64
evaluation rounded once; a spike can differ only where
a membrane lies within float32 rounding of the threshold.

Limits. Step indices are int64: a ``dt`` that would cut the stream into more than ``2 ** 62``
steps is refused, and a ``dt`` longer than the stream puts every event in step 0. The output
is counted before it is built; more events than the limit in force
(:func:`evdown_torch.max_output_events`; a neuron firing through a very long gap) are refused
with the expected count.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, cast

import torch
from torch import Tensor

from evdown_torch._tensors import (
    changes,
    divide,
    last_of_runs,
    run_index,
    stable_sort_small,
    where_true,
)
from evdown_torch.checks import output_size
from evdown_torch.events import Events, sort_by_time
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.lif.chains import Leak
from evdown_torch.transforms.functional.lif.closed_form import MIN_ROUNDS, certain_spikes
from evdown_torch.transforms.functional.lif.keys import (
    counted_cells,
    grouped_cells,
    spikes_by_step,
)
from evdown_torch.transforms.functional.lif.rounds import membranes_by_rounds, spikes_and_runs
from evdown_torch.transforms.functional.lif.settings import (
    DEFAULT_DT,
    DEFAULT_TAU,
    DEFAULT_THRESHOLD,
    DEFAULT_WEIGHT,
    RESET_MECHANISMS,
    LIFSettings,
    ResetMechanism,
    decay_factor,
)
from evdown_torch.transforms.functional.lif.steps import (
    MAX_STEPS,
    StepRuns,
    Steps,
    batch_step_indices,
    each_step,
    spikes_to_events,
    step_end_time,
    step_indices,
)

__all__ = [
    "DEFAULT_DT",
    "DEFAULT_TAU",
    "DEFAULT_THRESHOLD",
    "DEFAULT_WEIGHT",
    "MAX_STEPS",
    "RESET_MECHANISMS",
    "ResetMechanism",
    "LIFSettings",
    "LIFState",
    "decay_factor",
    "lif_pooling",
    "lif_spikes",
]

#: Most ``(region, step)`` keys per event, and in all, for which the cells are found in a
#: table of every key (a bool and an int32 running count each: at most 160 bytes per event,
#: 5 MB in all) rather than by sorting the events. Larger tables cost more than the sort: on
#: 6 s recordings of 200k events at 128x128 (1.5M to 6M keys) the table made a call about
#: 1.1 to 1.3x slower.
OCCUPANCY_KEYS_PER_EVENT = 32
MAX_OCCUPANCY_KEYS = 1 << 20
#: Most keys per event for which every key's events are counted instead (a live chunk: 1.5 ms
#: instead of 2.9 for 400k events on 10k keys; 4x slower than the table at 10 keys per event).
COUNTED_KEYS_PER_EVENT = 1


def _event_cells(
    events: Events | Sequence[Events],
    steps: Steps | Sequence[Steps],
    *,
    fx: int,
    fy: int,
    wo: int,
    plane: int,
    top_step: int,
    weight: float,
    mutual_inhibition: float,
    ascending: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Cells: the ``(region, step)`` pairs that hold events, ordered by region, then step.

    The events come whole or in time-ordered pieces (a streaming session's pending events,
    then its new chunk's), with the steps of each. A cell's key is
    ``region * span + (step - low)``, ``low`` the events' earliest step and
    ``span = top_step - low + 1`` (steps relative to the call's first, so that a streaming
    session's keys do not grow with the stream's age). Where there are few keys next to the
    events (:data:`COUNTED_KEYS_PER_EVENT`: a live chunk), every key's events are counted
    (:func:`~evdown_torch.transforms.functional.lif.keys.counted_cells`, piece by piece).
    Otherwise the pieces are joined; where there are few keys
    (:data:`OCCUPANCY_KEYS_PER_EVENT` per event and :data:`MAX_OCCUPANCY_KEYS` in all), the
    cells are the occupied entries of a bool table of every key, found without sorting the
    events (its running count gives every event's cell); otherwise the events are sorted by
    key (the order of the events within a cell does not matter: only their counts are kept),
    or, where the key would not fit in int64, stably by region (the events are in time order
    within a region).

    ``ascending``: every piece's steps ascend (one stream's time-sorted events), so the
    earliest step is a piece's first.

    Returns:
        ``(cell_region, cell_step, current)``: int64, int64 and the ``(n_cells, 2)`` float32
        input current of the region's (OFF, ON) neurons, ``w * S - w_inh * S'``.
    """
    if isinstance(events, Events):
        events, steps = [events], [cast(Tensor, steps)]
    device = events[0].device
    f32 = torch.float32
    pieces = [(e, s) for e, s in zip(events, cast(Sequence[Steps], steps), strict=True)
              if e.num_events]
    if not pieces:
        empty = torch.empty(0, dtype=torch.int64, device=device)
        return empty, empty, torch.empty(0, 2, dtype=f32, device=device)
    n = sum(e.num_events for e, _ in pieces)
    low = min(_lowest_step(s, ascending) for _, s in pieces)
    span = top_step - low + 1  # steps per region in the key
    n_keys = plane * span
    cell_region: Tensor | None = None
    if n_keys <= COUNTED_KEYS_PER_EVENT * n and 2 * n_keys < 1 << 31:  # count every key
        cell_step, counts = counted_cells(pieces, fx=fx, fy=fy, wo=wo, plane=plane, low=low,
                                          span=span)
    else:
        joined = pieces[0][0] if len(pieces) == 1 else Events.cat([e for e, _ in pieces])
        joined_steps = torch.cat([each_step(s) for _, s in pieces])
        cell_region, cell_step, counts = grouped_cells(
            joined, joined_steps, fx=fx, fy=fy, wo=wo, plane=plane, low=low, span=span,
            table=n_keys <= min(OCCUPANCY_KEYS_PER_EVENT * n, MAX_OCCUPANCY_KEYS))
    if cell_region is None:  # from the keys
        cell_region = divide(cell_step, span)
        cell_step = cell_step.sub_(cell_region * span).add_(low)
    counts = counts.to(f32)  # exact: fewer than 2**24 events per cell
    current = counts * torch.tensor(weight, dtype=f32, device=device)
    if mutual_inhibition != 0:
        current -= counts.flip(1) * torch.tensor(mutual_inhibition, dtype=f32, device=device)
    return cell_region, cell_step, current


def _lowest_step(steps: Steps, ascending: bool) -> int:
    """The earliest step of a piece's (non-empty) steps."""
    if isinstance(steps, StepRuns):  # its first run with events
        return steps.first + int(torch.argmax((steps.counts > 0).to(torch.int8)))
    return int(steps[0] if ascending else steps.min())


def _with_state_cells(
    cell_region: Tensor,
    cell_step: Tensor,
    current: Tensor,
    state: LIFState,
    *,
    plane: int,
    chains: bool,
    threshold32: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """The cells, each region's last update in ``state`` put in front of its cells.

    A state cell sits at the region's last updated step with the membrane as its "current"
    (from rest, one update gives ``beta * 0 + I = I``), so the rounds continue from it exactly
    as from an ordinary cell. Regions get one where they have cells, and, when the reset lets a
    neuron fire through empty steps (``chains``), where a neuron is above threshold.
    """
    if use_compiled(cell_region):  # one compiled merge: the same cells
        from evdown_torch.transforms.functional.compiled import lif_cells

        return lif_cells.with_state_cells(cell_region, cell_step, current, state,
                                          chains=chains, threshold=float(threshold32))
    wanted = torch.zeros(plane, dtype=torch.bool, device=cell_region.device)
    wanted[cell_region] = True
    if chains:
        wanted |= (state.membrane > threshold32).any(1)
    wanted &= state.last_step >= 0
    region = where_true(wanted)
    if region.shape[0] == 0:
        return cell_region, cell_step, current
    cell_region = torch.cat([region, cell_region])
    order = stable_sort_small(cell_region, plane)[1]  # stable: the state cell first
    return (
        cell_region.index_select(0, order),
        torch.cat([state.last_step.index_select(0, region), cell_step]).index_select(0, order),
        torch.cat([state.membrane.index_select(0, region), current]).index_select(0, order),
    )


def lif_pooling(
    events: Events,
    settings: LIFSettings,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    recording_spans: tuple[Tensor, Tensor] | None = None,
) -> Events:
    """Downscale a stream through one leaky integrate-and-fire neuron per region and polarity.

    The stream is binned into steps of ``dt`` from ``t_start`` (its first timestamp); the
    events of a step are pooled as :class:`~evdown_torch.models.SpikingPooling` pools a
    ``ToFrame`` tensor (weight ``+weight`` from the same polarity, ``-mutual_inhibition`` from
    the other), then ``snntorch.Leaky`` semantics run over every step from 0 to the step of
    ``t_end``. A spike of the neuron of polarity ``c`` and region ``(i, j)`` in step ``k``
    becomes the event ``(x=j, y=i, t=t_start + (k + 1) * dt clipped to t_end, p=c)``. The cost
    follows the events, not the steps (see the module docstring).

    Args:
        events: ``N`` events (any order); ``t`` int64 or float64.
        settings: the neuron's settings (``dt`` in the unit of ``t``).
        sensor_size: input sensor ``(W, H, P)``.
        factor: ``(fx, fy)``, positive integers.
        recording_spans: for a batch of ``B`` recordings stacked vertically (recording
            ``b``'s pixel ``(x, y)`` given as ``(x, y + b * Ho * fy)``, see
            ``transforms.functional.batch``), the ``(B,)`` first and last
            timestamps of each recording: each is binned from its own ``t_start`` and its
            spikes end at its own ``t_end``; the output is then sorted by recording, then
            step. ``None`` for one stream.

    Returns:
        Output events sorted by ``t`` (within a step: OFF before ON, then row-major region),
        ``t`` of the input's dtype, on the input's device.

    Raises:
        ValueError: when the steps cannot be indexed in int64 (``dt`` far too small for the
            stream's span) or the output would exceed the limit in force
            (:func:`evdown_torch.max_output_events`).

    Example:
        >>> ev = Events.from_columns([0, 1, 0, 1, 3], [0, 0, 1, 1, 0], [0, 1, 2, 3, 9],
        ...                          [1, 1, 1, 1, 0])
        >>> settings = LIFSettings(dt=2, beta=1.0, threshold=1.0, weight=0.3)
        >>> out = lif_pooling(ev, settings, sensor_size=(4, 2, 2), factor=(2, 2))
        >>> out.x.tolist(), out.y.tolist(), out.t.tolist(), out.p.tolist()
        ([0], [0], [4], [True])
    """
    events = sort_by_time(events)
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device)
    wo, ho, _ = output_size(sensor_size, factor)
    last_step: int | Tensor  # the stream's last step, or each recording's
    if recording_spans is None:
        steps, last_step, dt = step_indices(events.t, settings.dt)
        num_recordings = 1
    else:  # one block of Ho * Wo regions per recording
        steps, last_step, dt = batch_step_indices(  # each event's recording: its row block
            events.t, divide(events.y, ho * factor[1]), recording_spans, settings.dt)
        num_recordings = recording_spans[0].shape[0]
    spike_step, neuron, _ = lif_spikes(
        events, steps, settings, state=None, last_step=last_step, from_step=0,
        sensor_size=sensor_size, factor=factor, num_recordings=num_recordings, keep_state=False,
    )
    if recording_spans is None:
        t = step_end_time(spike_step, t_start=events.t[0], t_end=events.t[-1], dt=dt)
    else:  # recording by recording, each at its own clock
        starts, ends = recording_spans
        recording = divide(torch.remainder(neuron, num_recordings * wo * ho), wo * ho)
        recording, by_recording = stable_sort_small(recording, num_recordings)
        spike_step, neuron = spike_step[by_recording], neuron[by_recording]
        t = step_end_time(spike_step, t_start=starts.index_select(0, recording),
                           t_end=ends.index_select(0, recording), dt=dt)
    return spikes_to_events(spike_step, neuron, t, sensor_size=sensor_size, factor=factor,
                            num_recordings=num_recordings)


class LIFState(NamedTuple):
    """The neurons between two calls of :func:`lif_spikes` (a streaming session's state).

    A region's two neurons are updated together at the steps where the region has input, so
    the state is each region's membranes after its last updated step, and that step.

    Attributes:
        membrane: ``(Ho * Wo, 2)`` float32 membranes (OFF, ON) after step ``last_step``.
        last_step: ``(Ho * Wo,)`` int64 step of the region's last input, -1 for none yet.
    """

    membrane: Tensor
    last_step: Tensor


def initial_state(plane: int, device: torch.device | str | None = None) -> LIFState:
    """Every neuron at rest (membrane 0), none updated yet, for ``plane = Ho * Wo`` regions."""
    return LIFState(
        torch.zeros(plane, 2, dtype=torch.float32, device=device),
        torch.full((plane,), -1, dtype=torch.int64, device=device),
    )


def lif_spikes(
    events: Events | Sequence[Events],
    steps: Steps | Sequence[Steps],
    settings: LIFSettings,
    *,
    state: LIFState | None,
    last_step: int | Tensor,
    from_step: int,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    num_recordings: int = 1,
    keep_state: bool = True,
) -> tuple[Tensor, Tensor, LIFState | None]:
    """The spikes of the neurons over steps ``0 .. last_step``, from a state, event-driven.

    The core of :func:`lif_pooling` (``state=None``, ``from_step=0``) and of its streaming
    session (:mod:`evdown_torch.transforms.functional.lif.stream`), which continues from the
    neurons of the steps processed so far and processes up to a bound.

    Args:
        events: time-sorted events, all in steps after every region's ``state.last_step``
            and at most ``last_step``; or consecutive pieces of them (not joined here).
        steps: ``(N,)`` int64 step of every event (of every piece), or a piece's
            :class:`~.steps.StepRuns`.
        settings: the neuron's settings (its ``dt`` is not used: ``steps`` are given).
        state: the neurons before these events (``None``: all at rest).
        last_step: the last step to process: firing chains through the empty steps after a
            region's last input run up to it; for a batch, a ``(B,)`` tensor, each
            recording's own last step.
        from_step: return only the spikes of steps ``>= from_step`` (those of earlier steps
            were returned by an earlier call; they are neither built nor counted).
        sensor_size: input sensor ``(W, H, P)``.
        factor: ``(fx, fy)``, positive integers.
        num_recordings: how many recordings are stacked vertically in ``events`` (see
            :func:`lif_pooling`'s ``recording_spans``); a state is for one recording only.
        keep_state: return the neurons after the events; ``False`` returns ``None`` instead
            and lets a small call compute its spikes in closed form
            (:mod:`~evdown_torch.transforms.functional.lif.closed_form`), same spikes.

    Returns:
        ``(spike_step, neuron, state)``: int64 steps and neurons (``polarity * Ho * Wo +
        region``) of the spikes, sorted by step, then neuron; the neurons after the events
        (``None`` unless ``keep_state``).
    """
    beta, threshold, weight, mutual_inhibition, reset_mechanism = settings.constants
    fx, fy = factor
    wo, ho, _ = output_size(sensor_size, factor)
    plane = num_recordings * wo * ho  # num_recordings recordings stacked vertically
    top_step = int(last_step.max()) if isinstance(last_step, Tensor) else last_step
    cell_region, cell_step, current = _event_cells(
        events, steps, fx=fx, fy=fy, wo=wo, plane=plane, top_step=top_step, weight=weight,
        mutual_inhibition=mutual_inhibition, ascending=num_recordings == 1,
    )
    device, f32 = current.device, torch.float32
    beta32 = torch.tensor(beta, dtype=f32, device=device)  # the neuron's buffers, as snntorch
    threshold32 = torch.tensor(threshold, dtype=f32, device=device)
    leak = Leak(beta32, threshold32, reset_mechanism)
    if state is not None:  # each region's last update, as a cell whose current is its membrane
        cell_region, cell_step, current = _with_state_cells(
            cell_region, cell_step, current, state, plane=plane,
            chains=reset_mechanism != "zero", threshold32=threshold32,
        )
    n_cells = cell_region.shape[0]
    if n_cells == 0:
        empty = torch.empty(0, dtype=torch.int64, device=device)
        if not keep_state:
            return empty, empty, None
        return empty, empty, state if state is not None else initial_state(plane, device)

    # Each region's cells: its first one, and the empty steps before and after each cell.
    new_region = changes(cell_region)
    region_first = where_true(new_region)
    region_last = last_of_runs(region_first, n_cells)
    cells_per_region = region_last - region_first + 1
    gap_after = torch.empty_like(cell_step)
    torch.sub(cell_step[1:], cell_step[:-1], out=gap_after[:-1]).sub_(1)
    if isinstance(last_step, Tensor):  # a batch: each region's own recording's last step
        last_step = last_step.index_select(
            0, divide(cell_region.index_select(0, region_last), wo * ho))
    gap_after.index_copy_(0, region_last, last_step - cell_step.index_select(0, region_last))

    # The membranes: in closed form where that is certain to give the rounds' spikes (calls
    # whose new state is not needed), else by rounds (on the CPU, a compiled loop cell by cell:
    # cheaper than the closed form, the same spikes).
    rounds = int(cells_per_region.max())
    certain = None
    if not keep_state and rounds >= MIN_ROUNDS and not use_compiled(current):
        certain = certain_spikes(cell_step, current, region_first, run_index(new_region),
                                 cells_per_region, gap_after, rounds=rounds, leak=leak)
    if certain is not None:
        spikes, membrane = certain, None
    else:
        gap_before = torch.empty_like(gap_after)
        gap_before[1:] = gap_after[:-1]
        gap_before.index_copy_(0, region_first, cell_step.index_select(0, region_first))  # from 0
        membrane, chain_before = membranes_by_rounds(
            current, gap_before, region_first, new_region, cells_per_region, rounds=rounds,
            leak=leak,
        )
        spikes = spikes_and_runs(membrane, chain_before, cell_step, gap_before, gap_after,
                                 region_last, leak=leak)
    del current, new_region
    # Output order: by step, then neuron (OFF before ON, then row-major region).
    spike_step, neuron = spikes_by_step(spikes, cell_step, cell_region, plane=plane,
                                        from_step=from_step, top_step=top_step)
    if not keep_state or membrane is None:  # (no membranes: the closed form, no state kept)
        return spike_step, neuron, None
    # The neurons after the last update of every region here.
    last_region = cell_region.index_select(0, region_last)
    if state is None:
        state = initial_state(plane, device)
    state = LIFState(
        state.membrane.index_put((last_region,), membrane.index_select(0, region_last)),
        state.last_step.index_put((last_region,), cell_step.index_select(0, region_last)),
    )
    return spike_step, neuron, state

