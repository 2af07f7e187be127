"""EventCount: the paper's log-luminance event count, causal and streamable."""

from __future__ import annotations

from dataclasses import dataclass

from evdown_torch.collate import EventBatch
from evdown_torch.events import Events
from evdown_torch.transforms._base import Session, ThresholdDownscaler
from evdown_torch.transforms._batch import Stacked, run_stacked, sorted_within
from evdown_torch.transforms.functional.event_count import (
    EventCountState,
    event_count,
    event_count_batch,
    event_count_sorted,
)


@dataclass(frozen=True)
class EventCount(ThresholdDownscaler):
    """Log-luminance event count (docs/semantics.md, method 3), integer-exact and causal.

    Each input pixel keeps an integer level (ON +1, OFF -1); after each input event its
    region's mean level is tested with the DVS reference rule at contrast ``threshold``, and
    emitted events take the triggering event's timestamp.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        threshold: contrast threshold on the region's mean level (in input events per pixel),
            > 0. It is used as the nearest fraction with denominator at most 10**6, so decimal
            thresholds such as 0.01 are exact.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 10, 1], [1, 1, 20, 1], [0, 1, 30, -1], [1, 0, 40, -1]])
        >>> EventCount((2, 2, 2), factor=2, threshold=0.5)(ev).tolist()
        [[0, 0, 20, 1], [0, 0, 40, -1]]
    """

    def kernel(self, events: Events) -> Events:
        """Apply :func:`~evdown_torch.transforms.functional.event_count.event_count`."""
        out, _ = event_count(
            events, sensor_size=self.sensor_size, factor=self.factor_xy, threshold=self.threshold
        )
        return out

    def batch_kernel(self, batch: EventBatch) -> EventBatch:
        """The kernel once on the batch, with one block of regions per recording (recordings
        in time order need no stacking: :func:`event_count_batch`)."""
        if sorted_within(batch.events.t, batch.lengths):
            return EventBatch(*event_count_batch(
                batch.events, batch.lengths, sensor_size=self.sensor_size,
                factor=self.factor_xy, threshold=self.threshold))

        def kernel(stacked: Stacked) -> Events:
            out, _ = event_count(
                stacked.events, sensor_size=self.sensor_size, factor=self.factor_xy,
                threshold=self.threshold, recordings=stacked.recordings,
            )
            return out

        return run_stacked(batch, kernel, sensor_size=self.sensor_size, factor=self.factor_xy)

    def stream(
        self, events: Events, state: EventCountState | None
    ) -> tuple[Events, EventCountState]:
        """One chunk of a stream: causal, so every output is decided by its chunk.

        The state (:class:`~evdown_torch.transforms.functional.event_count.EventCountState`)
        holds each region's level sum and reference index.
        """
        return event_count_sorted(
            events,
            sensor_size=self.sensor_size,
            factor=self.factor_xy,
            threshold=self.threshold,
            state=state,
        )


#: The EventCount session is the common :class:`~evdown_torch.transforms._base.Session`.
EventCountSession = Session
