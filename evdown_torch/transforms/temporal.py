"""TemporalFunnelling: temporal downscaling, composable with every spatial method."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from evdown_torch.checks import check_positive_float, check_sensor_size
from evdown_torch.events import Events, EventsLike, from_events, to_events
from evdown_torch.transforms._base import Streaming
from evdown_torch.transforms.functional.funnelling import last_instant
from evdown_torch.transforms.functional.temporal import temporal_funnelling


class TemporalState(NamedTuple):
    """State of a temporal funnelling stream between chunks.

    Attributes:
        t_start: the stream's first timestamp, origin of the bins.
        last_bin: the distinct events kept in the latest bin so far (binned ``t``).
    """

    t_start: int | float
    last_bin: Events


@dataclass(frozen=True)
class TemporalFunnelling(Streaming):
    """Temporal funnelling (docs/semantics.md, method 8): the paper's temporal downscaling.

    Every ``t`` becomes the start of its bin of length ``dt`` (bins start at the stream's
    first timestamp), then events equal in ``(x, y, t, p)`` are dropped. Coordinates are
    unchanged, so it composes with every spatial method, before or after it:
    ``tonic.transforms.Compose`` for whole recordings, :class:`~evdown_torch.Chain` to stream
    the composition too.

    Args:
        dt: bin length in the stream's own time unit (microseconds for Tonic), > 0; a whole
            number for integer timestamps (checked at call time). A ``dt`` longer than the
            recording (even beyond int64, e.g. ``1e300``) puts every event in one bin.
        sensor_size: ``(W, H, P)``; when given, coordinates are checked against it. The
            output sensor is the same.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 5, 1], [0, 0, 9, 1], [1, 0, 12, 1], [0, 0, 16, 1]])
        >>> TemporalFunnelling(dt=10)(ev).tolist()
        [[0, 0, 5, 1], [1, 0, 5, 1], [0, 0, 15, 1]]
    """

    dt: int | float
    sensor_size: tuple[int, int, int] | None = None

    def __post_init__(self) -> None:
        check_positive_float("dt", self.dt)
        if self.sensor_size is not None:
            object.__setattr__(self, "sensor_size", check_sensor_size(self.sensor_size))

    @property
    def output_sensor_size(self) -> tuple[int, int, int] | None:
        """The input sensor size: temporal funnelling does not move events in space."""
        return self.sensor_size

    def __call__(self, events: EventsLike) -> EventsLike:
        """Funnel events of any accepted kind; returns the same kind, sorted by ``t``."""
        ev, fmt = to_events(events, self.sensor_size)
        return from_events(temporal_funnelling(ev, dt=self.dt), fmt)

    def stream(
        self, events: Events, state: TemporalState | None
    ) -> tuple[Events, TemporalState]:
        """One chunk of a stream: bins from the stream's first timestamp; the repeats a later
        chunk can make lie in the latest bin, whose kept events the state holds."""
        if state is None:
            t_start, seen = events.t[0].item(), None
        else:
            t_start, seen = state.t_start, state.last_bin
        out = temporal_funnelling(events, dt=self.dt, t_start=t_start, seen=seen)
        last_bin = last_instant(out, seen)
        return out, TemporalState(t_start, last_bin)
