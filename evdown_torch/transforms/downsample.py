"""Coordinate-division baselines: Downsample and EventFunnelling."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

from evdown_torch._tensors import region_of
from evdown_torch.checks import check_output_count
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events
from evdown_torch.transforms._base import Downscaler, Method
from evdown_torch.transforms._batch import run_stacked, sorted_within
from evdown_torch.transforms.functional.downsample import (
    KEEPS_EVERY_EVENT,
    downsample_init,
    downsample_step,
    downsample_whole,
)
from evdown_torch.transforms.functional.funnelling import (
    FUNNEL_FEWER,
    funnel_batch,
    funnel_init,
    funnel_step,
    funnel_whole,
)
from evdown_torch.transforms.functional.settings import RegionSettings


def _divided(batch: EventBatch, settings: RegionSettings) -> EventBatch:
    """Events do not interact: recordings each in time order need only the division."""
    events = batch.events
    check_output_count(events.num_events, fewer=KEEPS_EVERY_EVENT)
    x, y = region_of(events, settings.factor)
    return EventBatch(Events(x, y, events.t.clone(), events.p.clone()), batch.lengths)


def _funnelled(batch: EventBatch, settings: RegionSettings) -> EventBatch:
    """Recordings each in time order go through :func:`funnel_batch` (no stacking)."""
    width, height, _ = settings.output_sensor_size
    out = EventBatch(*funnel_batch(batch.events, batch.lengths, settings.factor, (width, height)))
    check_output_count(out.events.num_events, fewer=FUNNEL_FEWER)
    return out


def _stacked(
    sorted_kernel: Callable[[EventBatch, RegionSettings], EventBatch],
    whole: Callable[[Events, RegionSettings], Events],
) -> Callable[[EventBatch, RegionSettings], EventBatch]:
    """A batch kernel from a method's sorted and whole-stream kernels.

    ``sorted_kernel`` when every recording is in time order, else the whole-stream kernel once
    on the stacked recordings.
    """

    def stacked(batch: EventBatch, settings: RegionSettings) -> EventBatch:
        if sorted_within(batch.events.t, batch.lengths):
            return sorted_kernel(batch, settings)
        return run_stacked(batch, lambda s: whole(s.events, settings),
                           sensor_size=settings.sensor_size, factor=settings.factor)

    return stacked


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

    method: ClassVar[Method] = Method(downsample_init, downsample_step, whole=downsample_whole,
                                      stacked=_stacked(_divided, downsample_whole))


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

    method: ClassVar[Method] = Method(funnel_init, funnel_step, whole=funnel_whole,
                                      stacked=_stacked(_funnelled, funnel_whole))
