"""Coordinate-division baselines: Downsample and EventFunnelling."""

from __future__ import annotations

from dataclasses import dataclass

from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.functional.downsample import DOWNSAMPLE
from evdown_torch.transforms.functional.funnelling import FUNNELLING


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

    method = DOWNSAMPLE
    name = "downsample"


@dataclass(frozen=True)
class EventFunnelling(Downscaler):
    """Downsample, then drop every event equal in ``(x', y', t, p)`` to an earlier one.

    Args: as :class:`Downsample`.

    Example:
        Pixels (0, 0) and (1, 1) fire ON at once: one ON event of region (0, 0) is kept.

        >>> import torch
        >>> ev = torch.tensor([[0, 0, 7, 1], [1, 1, 7, 1], [1, 1, 7, 0]])
        >>> EventFunnelling((4, 4, 2), factor=2)(ev).tolist()
        [[0, 0, 7, 1], [0, 0, 7, 0]]
    """

    method = FUNNELLING
    name = "funnelling"
