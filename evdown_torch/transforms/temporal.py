"""TemporalFunnelling: temporal downscaling, composable with every spatial method."""

from __future__ import annotations

__all__ = ["TemporalFunnelling", "TemporalState"]

from dataclasses import dataclass
from functools import cached_property

from evdown_torch.transforms._base import Streaming
from evdown_torch.transforms.functional.temporal import (
    TEMPORAL_FUNNELLING,
    TemporalSettings,
    TemporalState,
)


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

    method = TEMPORAL_FUNNELLING
    name = "temporal"

    @cached_property
    def settings(self) -> TemporalSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return TemporalSettings(self.dt, self.sensor_size)

    @property
    def output_sensor_size(self) -> tuple[int, int, int] | None:
        """The input sensor size, as temporal funnelling does not move events in space."""
        return self.sensor_size
