"""Temporal funnelling kernel: timestamps to the start of their bin, then drop repeats."""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import divide
from evdown_torch.checks import check_output_count, check_positive_float, check_sensor_size
from evdown_torch.events import Events, sort_by_time
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.funnelling import drop_repeats, last_instant
from evdown_torch.transforms.functional.protocol import Method

__all__ = [
    "TEMPORAL_FUNNELLING",
    "TemporalSettings",
    "TemporalState",
    "bin_index",
    "bin_start",
    "temporal_funnelling",
    "temporal_funnelling_init",
    "temporal_funnelling_step",
    "temporal_funnelling_whole",
]

_INT64_MAX = torch.iinfo(torch.int64).max


def _whole(dt: int | float) -> bool:
    return isinstance(dt, numbers.Integral) or float(dt).is_integer()


def _span_error(t: Tensor, origin: int) -> ValueError:
    """int64 ``t`` whose offsets from ``origin`` wrap past ``2**63 - 1``."""
    return ValueError(
        f"the timestamps span 2**63 or more time units from {origin} (up to "
        f"{int(t.max())}): their offsets do not fit in int64"
    )


def _compiled_bins(t: Tensor, dt: int | float, t_start: int | float, *,
                   starts: bool) -> Tensor | None:
    """The bins (or their starts) of int64 ``t`` by the compiled loop on the CPU, else ``None``.

    ``None`` where the loop does not take them: other dtypes, no compiled path, a ``dt``
    that is not a whole number or exceeds int64. Raises the span error as the eager path.
    """
    if not (t.dtype == torch.int64 and use_compiled(t) and _whole(dt)
            and int(dt) <= _INT64_MAX):
        return None
    from evdown_torch.transforms.functional.compiled.temporal import bins

    out = bins(t.numpy(), int(t_start), int(dt), starts=starts)
    if out is None:
        raise _span_error(t, int(t_start))
    return torch.from_numpy(out)


def bin_index(t: Tensor, *, dt: int | float, t_start: int | float) -> Tensor:
    """``floor((t - t_start) / dt)``: the bin of each timestamp, bins of ``dt`` from ``t_start``.

    Args and errors as :func:`bin_start`; for float ``t`` also a ``ValueError`` when an index
    reaches ``2**62`` (a ``dt`` far too small for the stream's span).

    Returns:
        ``(N,)`` int64 bin indices; exact for int64 ``t``.

    Example:
        >>> bin_index(torch.tensor([3, 9, 13, 25]), dt=10, t_start=3).tolist()
        [0, 0, 1, 2]
        >>> bin_index(torch.tensor([0.5, 2.0]), dt=1.5, t_start=0.5).tolist()
        [0, 1]
    """
    if t.is_floating_point():
        index = torch.floor((t - t_start) / dt)
        if index.numel() and float(index.abs().max()) >= 2.0**62:
            raise ValueError(
                f"bins of {dt!r} time units number 2**62 or more over these timestamps: the "
                "bin length is far too small for the stream's span"
            )
        return index.to(torch.int64)
    if not _whole(dt):
        raise ValueError(
            f"dt must be a whole number for integer timestamps (bin starts must stay "
            f"integers), got {dt!r}"
        )
    compiled = _compiled_bins(t, dt, t_start, starts=False)
    if compiled is not None:
        return compiled
    origin = int(t_start)
    offset = t - origin
    if bool((offset < 0).any()):  # t >= t_start, so only a wrap past 2**63 - 1 is negative
        raise _span_error(t, origin)
    step = int(dt)
    if step > _INT64_MAX:  # longer than any offset: one bin (torch cannot take the int)
        return torch.zeros_like(t)
    return divide(offset, step)


def bin_start(t: Tensor, *, dt: int | float, t_start: int | float) -> Tensor:
    """``t_start + floor((t - t_start) / dt) * dt``: the start of each timestamp's bin.

    A ``dt`` longer than every span int64 ``t`` can have (``dt > 2**63 - 1``) puts every
    timestamp in the first bin, as it does for float ``t``: it is not refused.

    Args:
        t: ``(N,)`` int64 or float64 timestamps, ``>= t_start``.
        dt: bin length in the stream's time unit, > 0; an integer for int64 ``t``.
        t_start: the stream's first timestamp.

    Returns:
        ``(N,)`` bin starts, ``t``'s dtype; exact for int64 ``t``.

    Raises:
        ValueError: for int64 ``t`` and a ``dt`` that is not a whole number (its bin starts
            would not be integers), or int64 ``t`` spanning ``2**63`` or more from
            ``t_start`` (their offsets would wrap).

    Example:
        >>> bin_start(torch.tensor([3, 9, 10, 25]), dt=10, t_start=3).tolist()
        [3, 3, 3, 23]
        >>> bin_start(torch.tensor([3, 9, 2**62]), dt=1e300, t_start=3).tolist()
        [3, 3, 3]
    """
    if t.is_floating_point():
        return (torch.floor((t - t_start) / dt) * dt).add_(t_start)
    compiled = _compiled_bins(t, dt, t_start, starts=True)
    if compiled is not None:
        return compiled
    index = bin_index(t, dt=dt, t_start=t_start)
    step = int(dt)
    if step > _INT64_MAX:  # one bin, starting at t_start
        return index.add_(int(t_start))
    return index.mul_(step).add_(int(t_start))


def temporal_funnelling(
    events: Events,
    *,
    dt: int | float,
    t_start: int | float | None = None,
    seen: Events | None = None,
    size: tuple[int, int] | None = None,
) -> Events:
    """Temporal downscaling (docs/semantics.md, method 8).

    Every ``t`` becomes the start of its bin, ``t_start + floor((t - t_start) / dt) * dt``,
    and events equal in ``(x, y, t, p)`` after that are dropped (the first is kept);
    coordinates are unchanged.

    Args:
        events: ``N`` events (any order).
        dt: bin length in the stream's own time unit (microseconds for Tonic), > 0; a whole
            number for int64 timestamps.
        t_start: origin of the bins (default: the first timestamp of ``events``); a
            streaming session passes the stream's.
        seen: distinct events already kept in the bin of the first event (streaming).
        size: the sensor's ``(width, height)`` when known (every coordinate, ``seen``'s
            included, lies inside it); by default the largest coordinates + 1.

    Returns:
        The kept events with binned timestamps, sorted by ``t``.

    Example:
        >>> ev = Events.from_columns([0, 0, 1, 0], [0, 0, 0, 0], [5, 9, 12, 16], [1, 1, 1, 1])
        >>> out = temporal_funnelling(ev, dt=10)
        >>> out.x.tolist(), out.t.tolist()
        ([0, 1, 0], [5, 5, 15])
    """
    return _funnel_sorted(sort_by_time(events), dt, t_start, seen, size)


def _funnel_sorted(
    events: Events, dt: int | float, t_start: int | float | None, seen: Events | None,
    size: tuple[int, int] | None,
) -> Events:
    """:func:`temporal_funnelling` of events in stable time order (a session's chunk)."""
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device)
    if t_start is None:
        t_start = events.t[0].item()
    binned = Events(events.x, events.y, bin_start(events.t, dt=dt, t_start=t_start), events.p)
    return drop_repeats(binned, seen=seen, size=size)


@dataclass(frozen=True)
class TemporalSettings:
    """Temporal funnelling's settings, checked once.

    Attributes:
        dt: bin length in the stream's time unit, > 0 (a whole number for integer
            timestamps, checked at call time).
        sensor_size: ``(W, H, P)`` to check coordinates against, or ``None``.
    """

    dt: int | float
    sensor_size: tuple[int, int, int] | None = None

    def __post_init__(self) -> None:
        check_positive_float("dt", self.dt)
        if self.sensor_size is not None:
            object.__setattr__(self, "sensor_size", check_sensor_size(self.sensor_size))

    @property
    def size(self) -> tuple[int, int] | None:
        """The sensor's ``(W, H)``, which the transform checks every event against, or ``None``."""
        return None if self.sensor_size is None else self.sensor_size[:2]


class TemporalState(NamedTuple):
    """State of a temporal funnelling stream between chunks.

    Attributes:
        t_start: the stream's first timestamp, origin of the bins.
        last_bin: the distinct events kept in the latest bin so far (binned ``t``), ``None``
            before any.
    """

    t_start: int | float
    last_bin: Events | None


#: How TemporalFunnelling's output gets under the output limit (repeats share a bin).
TEMPORAL_FEWER = "a longer dt gives fewer events"


def temporal_funnelling_init(settings: TemporalSettings, events: Events) -> TemporalState:
    """``init_state``: the bins start at the first chunk's first timestamp."""
    return TemporalState(events.t[0].item(), None)


def temporal_funnelling_step(
    events: Events, state: TemporalState, settings: TemporalSettings
) -> tuple[Events, TemporalState]:
    """``step``: one time-sorted chunk.

    The repeats a later chunk can make lie in the latest bin, whose kept events the state
    holds.
    """
    out = _funnel_sorted(events, settings.dt, state.t_start, state.last_bin, settings.size)
    check_output_count(out.num_events, fewer=TEMPORAL_FEWER)  # at most the input: built already
    return out, TemporalState(state.t_start, last_instant(out, state.last_bin))


def temporal_funnelling_whole(events: Events, settings: TemporalSettings) -> Events:
    """The whole stream (any order): :func:`temporal_funnelling`."""
    out = temporal_funnelling(events, dt=settings.dt, size=settings.size)
    check_output_count(out.num_events, fewer=TEMPORAL_FEWER)  # at most the input: built already
    return out


#: TemporalFunnelling's kernels (:class:`~evdown_torch.TemporalFunnelling`).
TEMPORAL_FUNNELLING: Method[TemporalSettings, TemporalState] = Method(
    temporal_funnelling_init, temporal_funnelling_step, whole=temporal_funnelling_whole
)
