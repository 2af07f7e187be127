"""Coordinate-division baselines: Downsample and EventFunnelling."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from evdown_torch._tensors import region_of
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events
from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms._batch import run_stacked, sorted_within
from evdown_torch.transforms.functional.downsample import downsample
from evdown_torch.transforms.functional.funnelling import (
    event_funnelling,
    funnel_batch,
    funnel_sorted,
    last_instant,
)


@dataclass(frozen=True)
class Downsample(Downscaler):
    """Divide pixel coordinates by the factor and keep every event (Tonic-style baseline).

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.

    Example:
        >>> import numpy as np
        >>> dtype = np.dtype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")])
        >>> ev = np.array([(3, 1, True, 0), (2, 0, False, 5)], dtype=dtype)
        >>> down = Downsample((4, 4, 2), factor=2)
        >>> out = down(ev)
        >>> out.tolist(), down.output_sensor_size
        ([(1, 0, True, 0), (1, 0, False, 5)], (2, 2, 2))
    """

    def kernel(self, events: Events) -> Events:
        """Apply :func:`~evdown_torch.transforms.functional.downsample.downsample`."""
        return downsample(events, factor=self.factor_xy)

    def batch_kernel(self, batch: EventBatch) -> EventBatch:
        """Events do not interact: recordings in time order need only the division."""
        events = batch.events
        if sorted_within(events.t, batch.lengths):
            x, y = region_of(events, self.factor_xy)
            return EventBatch(Events(x, y, events.t.clone(), events.p.clone()), batch.lengths)
        return run_stacked(batch, lambda s: downsample(s.events, factor=self.factor_xy),
                           sensor_size=self.sensor_size, factor=self.factor_xy)
    def stream(self, events: Events, state: Any | None) -> tuple[Events, None]:
        """One chunk of a stream (already in time order): stateless, every event is decided
        at once."""
        x, y = region_of(events, self.factor_xy)
        return Events(x, y, events.t.clone(), events.p.clone()), None


@dataclass(frozen=True)
class EventFunnelling(Downscaler):
    """Downsample, then drop every event equal in ``(x', y', t, p)`` to an earlier one.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.

    Example:
        >>> import numpy as np
        >>> dtype = np.dtype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")])
        >>> ev = np.array([(0, 0, True, 7), (1, 1, True, 7), (1, 1, False, 7)], dtype=dtype)
        >>> EventFunnelling((4, 4, 2), factor=2)(ev).tolist()
        [(0, 0, True, 7), (0, 0, False, 7)]
    """

    def kernel(self, events: Events) -> Events:
        """Apply :func:`~evdown_torch.transforms.functional.funnelling.event_funnelling`."""
        return event_funnelling(events, factor=self.factor_xy)

    def batch_kernel(self, batch: EventBatch) -> EventBatch:
        """Recordings in time order go through :func:`funnel_batch` (no stacking); others
        through the kernel once on the stacked batch."""
        if sorted_within(batch.events.t, batch.lengths):
            width, height, _ = self.output_sensor_size
            return EventBatch(*funnel_batch(batch.events, batch.lengths, self.factor_xy,
                                            (width, height)))
        return run_stacked(batch, lambda s: event_funnelling(s.events, factor=self.factor_xy),
                           sensor_size=self.sensor_size, factor=self.factor_xy)
    def stream(self, events: Events, state: Events | None) -> tuple[Events, Events | None]:
        """One chunk of a stream.

        The state is the distinct output events at the latest timestamp so far: the only ones
        a later chunk can repeat (a repeat shares ``t``), so duplicates that straddle a chunk
        boundary are still dropped.
        """
        width, height, _ = self.output_sensor_size
        out = funnel_sorted(events, self.factor_xy, seen=state, size=(width, height))
        return out, last_instant(out, state)
