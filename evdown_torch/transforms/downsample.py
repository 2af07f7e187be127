"""Coordinate-division baselines: Downsample and EventFunnelling."""

from __future__ import annotations

from dataclasses import dataclass

from evdown_torch.events import Events
from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms._batch import Stacked
from evdown_torch.transforms.functional.downsample import downsample
from evdown_torch.transforms.functional.funnelling import event_funnelling


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

    def batch_kernel(self, stacked: Stacked) -> Events:
        """Regions are independent: the kernel runs on the stacked batch as it is."""
        return downsample(stacked.events, factor=self.factor_xy)


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

    def batch_kernel(self, stacked: Stacked) -> Events:
        """Regions are independent: the kernel runs on the stacked batch as it is."""
        return event_funnelling(stacked.events, factor=self.factor_xy)
