"""EventCount: the paper's log-luminance event count, causal and streamable."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from evdown_torch._tensors import sort_by_time
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events
from evdown_torch.transforms._base import Method, Session, ThresholdDownscaler
from evdown_torch.transforms._batch import Stacked, run_stacked, sorted_within
from evdown_torch.transforms.functional.event_count import (
    event_count_batch,
    event_count_init,
    event_count_step,
    event_count_whole,
    initial_state,
)
from evdown_torch.transforms.functional.settings import ThresholdSettings


def _stacked(batch: EventBatch, settings: ThresholdSettings) -> EventBatch:
    """The kernel once on the batch, with one block of regions per recording.

    Recordings in time order need no stacking (:func:`event_count_batch`).
    """
    if sorted_within(batch.events.t, batch.lengths):
        return EventBatch(*event_count_batch(batch.events, batch.lengths, settings))

    def kernel(stacked: Stacked) -> Events:
        state = initial_state(settings, stacked.events.device, stacked.recordings)
        out, _ = event_count_step(sort_by_time(stacked.events), state, settings)
        return out

    return run_stacked(batch, kernel, sensor_size=settings.sensor_size, factor=settings.factor)


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

    method: ClassVar[Method] = Method(event_count_init, event_count_step,
                                      whole=event_count_whole, stacked=_stacked)


#: The EventCount session is the common :class:`~evdown_torch.transforms._base.Session`.
EventCountSession = Session
