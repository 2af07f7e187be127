"""EventCount: the paper's log-luminance event count, with a streaming session."""

from __future__ import annotations

from dataclasses import dataclass

from evdown_torch.events import Events, EventsLike, from_events, to_events
from evdown_torch.transforms._base import ThresholdDownscaler
from evdown_torch.transforms.functional.event_count import (
    EventCountState,
    event_count,
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

    def session(self) -> EventCountSession:
        """Start a streaming session over consecutive chunks of one stream."""
        return EventCountSession(self)


class EventCountSession:
    """Streaming EventCount: feed consecutive chunks of a stream, get each chunk's events.

    The concatenation of the outputs equals ``EventCount`` applied to the whole stream.
    Chunks must follow each other in time (a chunk may not start before the previous one's
    last timestamp; equal timestamps are fine and keep chunk order). The session holds the
    per-region state explicitly in :attr:`state`; the transform itself is never modified.

    Args:
        transform: the :class:`EventCount` settings.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 10, 1], [1, 1, 20, 1], [0, 1, 30, -1], [1, 0, 40, -1]])
        >>> session = EventCount((2, 2, 2), factor=2, threshold=0.5).session()
        >>> [session(chunk).tolist() for chunk in (ev[:1], ev[1:3], ev[3:])]
        [[], [[0, 0, 20, 1]], [[0, 0, 40, -1]]]
    """

    def __init__(self, transform: EventCount) -> None:
        self.transform = transform
        self.state: EventCountState | None = None

    def reset(self) -> None:
        """Forget the stream: the next chunk starts a new one."""
        self.state = None

    def __call__(self, chunk: EventsLike) -> EventsLike:
        """Downscale the next chunk; returns the events it produces, in the chunk's kind."""
        transform = self.transform
        events, fmt = to_events(chunk, transform.sensor_size)
        if self.state is not None and self.state.last_t is not None and events.num_events:
            if self.state.last_t.device != events.device:
                raise ValueError(
                    f"chunk is on {events.device} but the session's state is on "
                    f"{self.state.last_t.device}"
                )
            first = events.t.min()
            if bool(first < self.state.last_t):
                raise ValueError(
                    f"chunks must follow each other in time: this chunk starts at {first.item()}, "
                    f"before the previous chunk's last event at {self.state.last_t.item()}"
                )
        out, state = event_count(
            events,
            sensor_size=transform.sensor_size,
            factor=transform.factor_xy,
            threshold=transform.threshold,
            state=self.state,
        )
        if events.num_events == 0 and self.state is not None:
            state = self.state
        self.state = state
        return from_events(out, fmt)
