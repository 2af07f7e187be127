"""Tonic's own event filters as peers at a budget: RefractoryPeriod and Decimation's kernels.

Each runs the filter through Tonic itself (``tonic.functional``, a dependency, not a copy: its
results are Tonic's, quirks included), on the input resolution, and then divides the kept
events' coordinates by the factor, like the subsamplers. Tonic's functions are per-event
Python loops over whole recordings and keep no state between calls: the bundles have a
whole-stream kernel only (no session; a batch goes one recording at a time).

The events go to Tonic as a structured array with one more field, each event's position, so
the kept events are known exactly (Tonic copies whole records) and come back from the input
itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from evdown_torch.checks import check_positive_float
from evdown_torch.events import Events, sort_by_time
from evdown_torch.transforms.functional.downsample import to_regions
from evdown_torch.transforms.functional.protocol import Method
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = [
    "TONIC_DECIMATION",
    "TONIC_REFRACTORY",
    "DecimationSettings",
    "RefractorySettings",
    "decimation_whole",
    "refractory_whole",
]

#: Why neither has a session.
WHOLE_RECORDINGS = ("Tonic's filter processes whole recordings and keeps no state between "
                    "calls")


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
    return to_regions(chosen, factor)


@dataclass(frozen=True)
class RefractorySettings(RegionSettings):
    """Tonic's refractory period: ``delta``, in the stream's time unit, > 0."""

    delta: float = 1_000.0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "delta", check_positive_float("delta", self.delta))


@dataclass(frozen=True)
class DecimationSettings(RegionSettings):
    """Tonic's decimation: keep one event in ``n`` per pixel (a real ``n`` is rounded, >= 1)."""

    n: float = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        n = check_positive_float("n", self.n)
        if n < 0.5:
            raise ValueError(f"n must be at least 1 (one event kept in n), got {self.n!r}")
        object.__setattr__(self, "n", max(1, round(n)))


def refractory_whole(events: Events, settings: RefractorySettings) -> Events:
    """Tonic's refractory period filter on ``events`` (any order), then Downsample."""
    functional = _tonic_functional()
    return _through_tonic(
        events, lambda records: functional.refractory_period_numpy(records, settings.delta),
        settings.factor)


def decimation_whole(events: Events, settings: DecimationSettings) -> Events:
    """Tonic's decimation of ``events`` (any order), then Downsample."""
    functional = _tonic_functional()
    n = int(settings.n)
    return _through_tonic(events, lambda records: functional.decimate_numpy(records, n),
                          settings.factor)


#: TonicRefractoryPeriod's kernel (:class:`~evdown_torch.transforms.TonicRefractoryPeriod`).
TONIC_REFRACTORY: Method[RefractorySettings, None] = Method(
    whole=refractory_whole, no_stream=WHOLE_RECORDINGS)
#: TonicDecimation's kernel (:class:`~evdown_torch.transforms.TonicDecimation`).
TONIC_DECIMATION: Method[DecimationSettings, None] = Method(
    whole=decimation_whole, no_stream=WHOLE_RECORDINGS)
