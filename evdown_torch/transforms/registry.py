"""The downscaling methods by name, for the command line, the evaluation and the benchmarks."""

from __future__ import annotations

from dataclasses import fields
from typing import Any

from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.downsample import Downsample, EventFunnelling
from evdown_torch.transforms.estimation import CubicEstimation, LinearEstimation
from evdown_torch.transforms.event_count import EventCount
from evdown_torch.transforms.lif import LIFPooling
from evdown_torch.transforms.photocurrent import PhotocurrentPooling
from evdown_torch.transforms.subsampling import DensitySubsampling, PoissonSubsampling
from evdown_torch.transforms.tonic_peers import TonicDecimation, TonicRefractoryPeriod

#: Method name (each class's ``name``) -> transform class, in the paper's order: the spatial
#: downscalers, each built as ``cls(sensor_size, factor, **settings)`` and compared at every
#: factor by the evaluation and the benchmarks; then the subsamplers, peers that keep input
#: events at a budget and Downsample them (docs/semantics.md, methods 9 and 10, and Tonic's
#: RefractoryPeriod and Decimation through Tonic itself). TemporalFunnelling (method 8) is not
#: one of them: it has no factor and is composed with a spatial method (``evdown_torch.Chain``
#: or Tonic's ``Compose``), so the real-time benchmark names it in its own line-up
#: (``bench.realtime.REALTIME_METHODS``).
METHODS: dict[str, type[Downscaler]] = {
    cls.name: cls
    for cls in (Downsample, EventFunnelling, EventCount, LinearEstimation, CubicEstimation,
                LIFPooling, PhotocurrentPooling, DensitySubsampling, PoissonSubsampling,
                TonicRefractoryPeriod, TonicDecimation)
}


def method_settings(name: str) -> tuple[str, ...]:
    """Names of the settings a method takes besides ``sensor_size`` and ``factor``."""
    cls = _method_class(name)
    return tuple(f.name for f in fields(cls) if f.name not in ("sensor_size", "factor"))


def _method_class(name: str) -> type[Downscaler]:
    if not isinstance(name, str) or name not in METHODS:
        raise ValueError(f"unknown method {name!r}; expected one of {sorted(METHODS)}")
    return METHODS[name]


def make_method(
    name: str, sensor_size: tuple[int, int, int], factor: int | tuple[int, int], **settings: Any
) -> Downscaler:
    """Build a downscaling transform by name.

    Args:
        name: one of :data:`METHODS`.
        sensor_size: input ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        **settings: the method's own settings (e.g. ``threshold``); see :func:`method_settings`.

    Returns:
        The transform.

    Raises:
        ValueError: for an unknown method or a setting the method does not take.

    Example:
        >>> make_method("event_count", (34, 34, 2), 2, threshold=0.5).output_sensor_size
        (17, 17, 2)
    """
    cls = _method_class(name)
    allowed = method_settings(name)
    unknown = sorted(set(settings) - set(allowed))
    if unknown:
        raise ValueError(
            f"method {name!r} does not take setting(s) {unknown}; it takes {list(allowed)}"
        )
    return cls(sensor_size, factor, **settings)
