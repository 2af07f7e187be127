"""RateLimiter: a hard cap on the output rate, composable after any method."""

from __future__ import annotations

__all__ = ["RateLimitState", "RateLimiter"]

from dataclasses import dataclass
from functools import cached_property

from evdown_torch.transforms._base import Streaming
from evdown_torch.transforms.functional.rate_limit import (
    RATE_LIMIT,
    RateLimitSettings,
    RateLimitState,
)


@dataclass(frozen=True)
class RateLimiter(Streaming):
    """A token bucket of ``max_events`` per ``window`` that drops what overflows.

    The bucket holds up to ``max_events`` tokens, starts full at the stream's first event and
    refills continuously at ``max_events`` per ``window``; an event passes when a whole token
    is there and takes it, else it is dropped (docs/semantics.md, "Rate limiter"). So no
    interval of length ``d`` passes more than ``max_events * (1 + d / window)`` events: a
    chip's input FIFO of depth ``max_events``, drained at ``max_events`` per ``window``, never
    overflows. Exact for integer timestamps; a session equals the call whatever the chunks,
    and its state counts the events dropped (``session.state.dropped``).

    Coordinates are unchanged: put it after any method, in :class:`~evdown_torch.Chain`
    (which streams the composition) or in ``tonic.transforms.Compose``.

    Args:
        max_events: the events a full bucket lets through at once, and the refill per
            ``window``; a positive integer.
        window: in the stream's own time unit (microseconds for Tonic), > 0; a whole number
            for integer timestamps (checked at call time).
        sensor_size: ``(W, H, P)``; when given, coordinates are checked against it. The
            output sensor is the same.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, t, 1] for t in (0, 0, 0, 1, 2, 5, 6)])
        >>> limiter = RateLimiter(max_events=2, window=4)   # 2 events, then 1 per 2 us
        >>> limiter(ev)[:, 2].tolist()
        [0, 0, 2, 5, 6]
        >>> session = limiter.session()
        >>> [len(session(chunk)) for chunk in (ev[:4], ev[4:])], session.state.dropped
        ([2, 3], 2)
    """

    max_events: int
    window: int | float
    sensor_size: tuple[int, int, int] | None = None

    method = RATE_LIMIT
    name = "rate_limit"

    @cached_property
    def settings(self) -> RateLimitSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return RateLimitSettings(self.max_events, self.window, self.sensor_size)

    @property
    def output_sensor_size(self) -> tuple[int, int, int] | None:
        """The input sensor size, as the limiter does not move events."""
        return self.sensor_size
