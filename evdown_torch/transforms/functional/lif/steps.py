"""LIF pooling's clock: the step of every event, the last step, and a spike's time and event.

A stream is cut into steps of ``dt`` from its ``t_start`` (its first timestamp, or each
recording's own in a batch); a spike in step ``k`` becomes an event at
``t_start + (k + 1) * dt`` clipped to ``t_end`` (docs/semantics.md, method 6). Integer
timestamps with a whole ``dt`` are stepped exactly in int64; settings whose steps int64 cannot
index are refused.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._regions import region_xy
from evdown_torch._tensors import runs_of
from evdown_torch.checks import output_size
from evdown_torch.events import Events

__all__ = [
    "MAX_STEPS",
    "StepRuns",
    "Steps",
    "batch_step_indices",
    "each_step",
    "spikes_to_events",
    "step_end_time",
    "step_indices",
    "step_runs",
]

#: Largest number of steps a stream may be cut into (step indices are int64, with headroom).
MAX_STEPS = 1 << 62

#: Fewest events, and fewest events per step spanned, for which a sorted stream's steps are
#: found by searching the steps' first times rather than by dividing every time (int64
#: division is slow): on 10 ms chunks of 400k events at ``dt`` = 1 ms, 0.3 ms instead of 0.8;
#: the search's cost grows with the steps, so 400k events over 10k steps divide (0.8 ms, 1.2
#: by the search).
SEARCH_MIN_EVENTS = 1 << 14
SEARCH_MIN_EVENTS_PER_STEP = 256


class StepRuns(NamedTuple):
    """The steps of time-sorted events as runs: ``counts[i]`` events in step ``first + i``.

    What :func:`step_runs` finds by searching, and :func:`step_indices` repeats over each
    run's events: a live chunk's steps in a few numbers, not one per event.

    Attributes:
        first: the step of the first run.
        counts: ``(S,)`` int64 events of each run (``0`` for an empty step), ``S >= 1``.

    Example:
        >>> runs = StepRuns(4, torch.tensor([2, 0, 3]))
        >>> runs.expand().tolist(), runs.last, runs.num_events
        ([4, 4, 6, 6, 6], 6, 5)
        >>> head, tail = runs.split(5)
        >>> head.expand().tolist(), tail.expand().tolist()
        ([4, 4], [6, 6, 6])
    """

    first: int
    counts: Tensor

    @property
    def num_events(self) -> int:
        """The events of all runs."""
        return int(self.counts.sum())

    @property
    def last(self) -> int:
        """The step of the last run (the last event's, where it has events)."""
        return self.first + self.counts.shape[0] - 1

    def expand(self) -> Tensor:
        """The ``(N,)`` int64 step of every event."""
        return runs_of(self.counts, self.num_events).add_(self.first)

    def split(self, step: int) -> tuple[StepRuns, StepRuns]:
        """The runs of steps below ``step`` and from ``step`` on (an empty one: no runs)."""
        cut = min(max(step - self.first, 0), self.counts.shape[0])
        return (StepRuns(self.first, self.counts[:cut]),
                StepRuns(self.first + cut, self.counts[cut:]))


#: A piece's steps: the ``(N,)`` int64 step of every event, or their :class:`StepRuns`.
Steps = Tensor | StepRuns


def each_step(steps: Steps) -> Tensor:
    """The ``(N,)`` int64 step of every event (:meth:`StepRuns.expand` of runs)."""
    return steps.expand() if isinstance(steps, StepRuns) else steps


def step_indices(
    t: Tensor, dt: float, t_start: Tensor | None = None
) -> tuple[Tensor, int, float]:
    """Step of every (sorted) event, the last step, and the ``dt`` to compute end times with.

    Steps count from ``t_start`` (default: the first event; a streaming session passes its
    stream's first timestamp), the last step is that of ``t[-1]``.

    Raises:
        ValueError: when the stream's span or its number of steps cannot be represented.
    """
    steps, last, dt = step_runs(t, dt, t_start)
    return each_step(steps), last, dt


def step_runs(
    t: Tensor, dt: float, t_start: Tensor | None = None
) -> tuple[Steps, int, float]:
    """:func:`step_indices`, with the steps as :class:`StepRuns` where found by searching.

    Many integer times and a whole ``dt`` (a live chunk's): the steps' runs; else the
    ``(N,)`` int64 step of every event.

    Raises:
        ValueError: when the stream's span or its number of steps cannot be represented.
    """
    if t_start is None:
        t_start = t[0]
    dt = _checked_dt(t_start, t[-1], t.is_floating_point(), dt, "the stream spans")
    found = _step_runs(t, int(t_start), int(dt)) if _searchable(t, dt) else None
    if found is not None:
        return found, found.last, dt
    steps = _steps(t - t_start, dt)
    return steps, int(steps[-1]), dt


def _searchable(t: Tensor, dt: float) -> bool:
    """Whether :func:`_step_runs` may step ``t``: integer times, a whole ``dt``, many events."""
    return (t.shape[0] >= SEARCH_MIN_EVENTS and not t.is_floating_point()
            and dt.is_integer())


def _step_runs(t: Tensor, t_start: int, dt: int) -> StepRuns | None:
    """``floor((t - t_start) / dt)`` of sorted int64 ``t`` by searching the steps' first times.

    Step ``k`` begins at ``t_start + k * dt`` exactly, so the events of a step are the run
    between two of those times: the runs' lengths (:meth:`StepRuns.expand` repeats each
    run's index over its events, the same integers as the division at a fraction of its
    cost). ``None`` where the events are fewer than :data:`SEARCH_MIN_EVENTS_PER_STEP` per
    step spanned (the division is cheaper there).
    """
    n = t.shape[0]
    first, last = (int(t[0]) - t_start) // dt, (int(t[-1]) - t_start) // dt
    if (last - first + 1) * SEARCH_MIN_EVENTS_PER_STEP > n:
        return None
    index = torch.arange(first, last + 1, device=t.device)
    begins = torch.searchsorted(t, index[1:] * dt + t_start)  # each later step's first event
    return StepRuns(first, torch.diff(begins, prepend=begins.new_zeros(1),
                                      append=begins.new_full((1,), n)))


def _checked_dt(
    t_start: Tensor | int, t_end: Tensor, floating: bool, dt: float, spans: str
) -> float:
    """The ``dt`` to compute steps with from ``t_start`` to ``t_end`` (``()`` tensors, or 0).

    Raises:
        ValueError: when the span or its number of steps cannot be represented (``spans``
            names the span in the message: "the stream spans" or "a recording spans").
    """
    if floating:
        span = float(t_end) - float(t_start)
        if not math.isfinite(span):
            raise ValueError(f"LIF pooling needs finite timestamps, got a span of {span}")
    else:
        span = int(t_end) - int(t_start)  # exact, as a Python int
        if span >= MAX_STEPS:
            raise ValueError(
                f"{spans} {span} time units, more than 2**62 that int64 step arithmetic can "
                "hold; split the stream"
            )
        if dt > span:  # one step holds everything; ends at t_start + dt > t_end, clipped
            dt = float(span + 1)
    if span / dt >= MAX_STEPS:
        whose = "the stream's" if spans.startswith("the") else "a recording's"
        raise ValueError(
            f"dt = {dt!r} cuts {whose} span of {span} time units into about "
            f"{span / dt:.3g} steps, more than the 2**62 an int64 step index can hold; "
            "use a larger dt"
        )
    return dt


def _steps(relative: Tensor, dt: float) -> Tensor:
    """``floor(relative / dt)`` as int64 (exact for integer times and a whole ``dt``)."""
    if not relative.is_floating_point() and dt.is_integer():
        return torch.div(relative, int(dt), rounding_mode="floor")
    return torch.floor(relative.to(torch.float64) / dt).to(torch.int64)


def batch_step_indices(
    t: Tensor, recording: Tensor, recording_spans: tuple[Tensor, Tensor], dt: float
) -> tuple[Tensor, Tensor, float]:
    """:func:`step_indices` for a batch.

    Each event's step from its own recording's ``t_start``, each recording's last step
    ``(B,)`` and the ``dt`` to compute end times with (see :func:`lif_pooling`).
    """
    starts, ends = recording_spans
    spans = ends - starts
    dt = _checked_dt(0, spans.max(), t.is_floating_point(), dt, "a recording spans")
    return _steps(t - starts.index_select(0, recording), dt), _steps(spans, dt), dt


def step_end_time(steps: Tensor, *, t_start: Tensor, t_end: Tensor, dt: float) -> Tensor:
    """Output timestamp ``t_start + (k + 1) * dt`` of steps ``k``, clipped to ``t_end``.

    Integer timestamps stay int64 and nothing overflows: with a whole ``dt`` the sum is exact;
    otherwise the offset ``(k + 1) * dt`` is rounded to the nearest integer, halves upward.
    """
    if t_start.is_floating_point():
        return torch.minimum(t_start + (steps + 1).to(torch.float64) * dt, t_end)
    span = t_end - t_start
    if dt.is_integer():
        start = steps * int(dt)  # <= span: the step begins inside the stream
        return torch.where(span - start > int(dt), t_start + start + int(dt), t_end)
    offset = torch.floor((steps + 1).to(torch.float64) * dt + 0.5)
    offset = torch.minimum(torch.minimum(offset, span.to(torch.float64)).to(torch.int64), span)
    return t_start + offset


def spikes_to_events(
    spike_step: Tensor,
    neuron: Tensor,
    t: Tensor,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    num_recordings: int = 1,
) -> Events:
    """Events of spikes of neurons ``polarity * plane + region`` at times ``t``.

    ``plane = num_recordings * Ho * Wo`` (``num_recordings`` recordings stacked vertically).
    """
    wo, ho, _ = output_size(sensor_size, factor)
    plane = num_recordings * wo * ho
    polarity = neuron >= plane
    x, y = region_xy(neuron - polarity * plane, wo)
    return Events(x, y, t, polarity)
