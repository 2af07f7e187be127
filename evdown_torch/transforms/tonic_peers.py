"""Tonic's own event filters as peers at a budget: RefractoryPeriod and Decimation, then Downsample.

Each transform here runs the filter through Tonic itself (``tonic.functional``, a dependency,
not a copy: its results are Tonic's, quirks included), on the input resolution, and then
divides the kept events' coordinates by the factor, like the subsamplers
(:mod:`evdown_torch.transforms.subsampling`). Each has one budget setting that
:func:`~evdown_torch.transforms.calibrate.calibrate` searches. Tonic's functions are per-event
Python loops over whole recordings and keep no state between calls: these transforms have no
streaming session and process a batch one recording at a time.

The events go to Tonic as a structured array with one more field, each event's position, so
the kept events are known exactly (Tonic copies whole records) and come back from the input
itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, NoReturn

import numpy as np
import torch

from evdown_torch._tensors import region_of, sort_by_time
from evdown_torch.checks import check_positive_float
from evdown_torch.events import Events
from evdown_torch.transforms._base import Downscaler

__all__ = ["TonicDecimation", "TonicRefractoryPeriod"]


def _tonic_functional() -> Any:
    """``tonic.functional``, or an ImportError saying how to install it."""
    try:
        import tonic.functional
    except ImportError:
        raise ImportError(
            "Tonic's RefractoryPeriod and Decimation need tonic: pip install "
            "'evdown_torch[tonic]'"
        ) from None
    return tonic.functional


def _through_tonic(events: Events, run: Any, factor: tuple[int, int]) -> Events:
    """``run`` (a Tonic filter on a structured array) on ``events``, then Downsample."""
    events = sort_by_time(events)
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device)
    t = events.t.detach().cpu().numpy()
    records = np.empty(events.num_events, dtype=[("x", np.int64), ("y", np.int64),
                                                  ("t", t.dtype), ("p", np.bool_),
                                                  ("i", np.int64)])
    records["x"] = events.x.cpu().numpy()
    records["y"] = events.y.cpu().numpy()
    records["t"] = t
    records["p"] = events.p.cpu().numpy()
    records["i"] = np.arange(events.num_events)
    kept = run(records)
    index = np.asarray(kept["i"] if len(kept) else np.empty(0), dtype=np.int64)
    chosen = events.select(torch.from_numpy(np.sort(index)).to(events.device))
    x, y = region_of(chosen, factor)
    return Events(x, y, chosen.t.clone(), chosen.p.clone())


class _WholeRecordings:
    """What both wrappers share: whole recordings only."""

    def session(self) -> NoReturn:
        """Not available: Tonic's filter takes whole recordings and keeps no state.

        Raises:
            NotImplementedError: always.
        """
        raise NotImplementedError(
            f"{type(self).__name__} has no streaming session: Tonic's filter processes whole "
            "recordings and keeps no state between calls"
        )


@dataclass(frozen=True)
class TonicRefractoryPeriod(_WholeRecordings, Downscaler):
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

    budget_setting: ClassVar[str | None] = "delta"

    delta: float = 1_000.0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "delta", check_positive_float("delta", self.delta))

    def kernel(self, events: Events) -> Events:
        """Tonic's refractory period filter on ``events`` (any order), then Downsample."""
        functional = _tonic_functional()
        return _through_tonic(
            events, lambda records: functional.refractory_period_numpy(records, self.delta),
            self.factor_xy)


@dataclass(frozen=True)
class TonicDecimation(_WholeRecordings, Downscaler):
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

    budget_setting: ClassVar[str | None] = "n"

    n: float = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        n = check_positive_float("n", self.n)
        if n < 0.5:
            raise ValueError(f"n must be at least 1 (one event kept in n), got {self.n!r}")
        object.__setattr__(self, "n", max(1, round(n)))

    def kernel(self, events: Events) -> Events:
        """Tonic's decimation of ``events`` (any order), then Downsample."""
        functional = _tonic_functional()
        n = int(self.n)
        return _through_tonic(events, lambda records: functional.decimate_numpy(records, n),
                              self.factor_xy)
