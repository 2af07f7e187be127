"""Tonic's own event filters as peers at a budget: RefractoryPeriod and Decimation, then Downsample.

Each runs the filter through Tonic itself on the input resolution, then divides the kept
events' coordinates by the factor, like the subsamplers
(:mod:`evdown_torch.transforms.subsampling`); their kernels
(``transforms.functional.tonic_peers``) take whole recordings only, so neither has a
streaming session. Each has one budget setting that
:func:`~evdown_torch.transforms.calibrate.calibrate` searches.
"""

from __future__ import annotations

__all__ = ["TonicDecimation", "TonicRefractoryPeriod"]

from dataclasses import dataclass
from functools import cached_property

from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.functional.tonic_peers import (
    TONIC_DECIMATION,
    TONIC_REFRACTORY,
    DecimationSettings,
    RefractorySettings,
)


@dataclass(frozen=True)
class TonicRefractoryPeriod(Downscaler):
    """``tonic.transforms.RefractoryPeriod(delta)`` at the input resolution, then Downsample.

    Tonic keeps an event iff more than ``delta`` has passed since the previous event at its
    pixel ``(x, y)`` (kept or not, either polarity); each pixel starts as if its last event
    were at ``-delta``, so a pixel's first event at ``t <= 0`` is dropped. ``delta`` is the
    budget setting (a longer period keeps fewer events).

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        delta: refractory period in the stream's time unit (microseconds for Tonic), > 0.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 10, 1], [0, 0, 15, 1], [0, 0, 30, 0], [3, 1, 31, 1]])
        >>> TonicRefractoryPeriod((4, 2, 2), factor=2, delta=10)(ev).tolist()
        [[0, 0, 10, 1], [0, 0, 30, 0], [1, 0, 31, 1]]
    """

    budget_setting = "delta"
    method = TONIC_REFRACTORY
    name = "refractory"

    delta: float = 1_000.0

    @cached_property
    def settings(self) -> RefractorySettings:
        """The checked settings the kernel takes (built once, in ``__post_init__``)."""
        return RefractorySettings(*self.region_geometry(), self.delta)


@dataclass(frozen=True)
class TonicDecimation(Downscaler):
    """``tonic.transforms.Decimation(n)`` at the input resolution, then Downsample.

    Tonic keeps the ``n``-th, ``2n``-th, ... event of each pixel ``(x, y)`` (either
    polarity). ``n`` is the budget setting; a real ``n`` is rounded to the nearest integer
    (at least 1), so that ``calibrate`` can search it.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        n: keep one event in ``n`` per pixel, >= 1.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 1, 1], [1, 0, 2, 1], [0, 0, 3, 0], [0, 0, 4, 1]])
        >>> TonicDecimation((2, 1, 2), factor=1, n=2)(ev).tolist()
        [[0, 0, 3, 0]]
    """

    budget_setting = "n"
    method = TONIC_DECIMATION
    name = "decimation"

    n: float = 2

    @cached_property
    def settings(self) -> DecimationSettings:
        """The checked settings the kernel takes (built once, in ``__post_init__``)."""
        return DecimationSettings(*self.region_geometry(), self.n)
