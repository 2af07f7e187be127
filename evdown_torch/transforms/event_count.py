"""EventCount: the paper's log-luminance event count, causal and streamable."""

from __future__ import annotations

from dataclasses import dataclass

from evdown_torch.transforms._base import ThresholdDownscaler
from evdown_torch.transforms.functional.event_count import EVENT_COUNT


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

    method = EVENT_COUNT
    name = "event_count"
