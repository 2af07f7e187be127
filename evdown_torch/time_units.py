"""Time units of event files, and the checks that catch a wrong one.

Kernels read timestamps in "the stream's time unit", and every default of the package (LIF's
``dt`` = 1 ms, ``tau`` = 10 ms, ``evdown show``'s 50 ms windows) assumes microseconds, the
unit of Tonic's datasets and of AEDAT4, N-MNIST and Prophesee files. Files in other units
(float seconds, as some N-Caltech101 conversions and several tools write them; nanoseconds)
are converted once, at the edge, with :func:`to_microseconds`.

A wrong unit shows itself in two ways that :func:`check_timing` warns about (a
:class:`TimeUnitWarning`): an implied event rate over :data:`MAX_PLAUSIBLE_RATE` (float seconds
read as microseconds put a whole recording inside a few microseconds), and a time setting
(``dt``, ``tau``, ``max_delay``, a window) longer than the whole recording.

:func:`display_unit` chooses seconds or milliseconds for showing times from a recording's start.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "MAX_PLAUSIBLE_RATE",
    "TIME_UNITS",
    "TimeUnitWarning",
    "check_unit_name",
    "check_timing",
    "display_unit",
    "time_settings",
    "to_microseconds",
]

#: Microseconds per unit, for each unit a file's timestamps may come in.
TIME_UNITS: dict[str, float] = {"s": 1e6, "ms": 1e3, "us": 1.0, "ns": 1e-3}

#: Event rates above this (events per second) are taken as a sign of a wrong time unit:
#: today's largest sensors peak at a few hundred million events per second.
MAX_PLAUSIBLE_RATE = 1e9

#: Fewer events than this say nothing about the rate (a burst may share one timestamp).
MIN_EVENTS_FOR_RATE = 100

#: Settings of the downscalers that are times in the stream's unit (microseconds here).
TIME_SETTINGS = ("dt", "tau", "max_delay", "window")


class TimeUnitWarning(UserWarning):
    """Timestamps or time settings that look like the wrong time unit."""


def check_unit_name(unit: Any) -> str:
    """Validate a time unit name: one of :data:`TIME_UNITS` (``"s"``, ``"ms"``, ``"us"``, ``"ns"``).

    Raises:
        ValueError: naming the units accepted.
    """
    if not isinstance(unit, str) or unit not in TIME_UNITS:
        raise ValueError(f"time unit must be one of {', '.join(TIME_UNITS)}, got {unit!r}")
    return unit


def to_microseconds(events: np.ndarray, unit: str) -> np.ndarray:
    """A copy of a structured event array with ``t`` in microseconds.

    Integer timestamps stay int64 where the conversion is exact (``s``, ``ms``, ``us``);
    nanoseconds and float timestamps become float64 microseconds.

    Args:
        events: ``(N,)`` structured array with a field ``t`` in ``unit``.
        unit: one of :data:`TIME_UNITS`.

    Returns:
        A new array, the same fields; ``t`` in microseconds (int64 or float64).

    Raises:
        ValueError: for an unknown unit, or integer times that overflow int64 in microseconds.

    Example:
        >>> import numpy as np
        >>> from evdown_torch.events import DVS_DTYPE
        >>> ev = np.zeros(2, [("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
        >>> ev["t"] = [0.5, 1.25]
        >>> to_microseconds(ev, "s")["t"].tolist()
        [500000.0, 1250000.0]
    """
    scale = TIME_UNITS[check_unit_name(unit)]
    t = events["t"]
    integer = np.issubdtype(t.dtype, np.integer)
    t_dtype = np.int64 if integer and scale >= 1 else np.float64
    names = events.dtype.names or ()
    dtype = np.dtype([(name, t_dtype if name == "t" else events.dtype[name]) for name in names])
    out = np.empty(events.shape, dtype=dtype)
    for name in names:
        out[name] = events[name]
    if t_dtype == np.int64:
        factor = int(scale)
        limit = np.iinfo(np.int64).max // factor
        if len(t) and max(abs(int(t.min())), abs(int(t.max()))) > limit:
            raise ValueError(f"timestamps in {unit} overflow int64 as microseconds")
        out["t"] = t.astype(np.int64) * factor
    else:
        out["t"] = t.astype(np.float64) * scale
    return out


def display_unit(span_us: float) -> tuple[str, float]:
    """The unit to show times of a recording spanning ``span_us`` microseconds in.

    Returns:
        ``("s", 1e6)`` for spans of a second or more, else ``("ms", 1e3)``: the name and the
        microseconds per unit (divide offsets from the recording's start by it).

    Example:
        >>> display_unit(300_000), display_unit(6e6)
        (('ms', 1000.0), ('s', 1000000.0))
    """
    return ("s", 1e6) if span_us >= 1e6 else ("ms", 1e3)


def time_settings(transform: Any) -> dict[str, float]:
    """The time settings of a downscaler, in the stream's unit.

    ``dt``, ``tau``, ``max_delay``, ``window`` and the frame period of ``fps``, leaving out
    those unset or infinite.
    """
    found = {}
    for name in TIME_SETTINGS:
        value = getattr(transform, name, None)
        if value is not None and math.isfinite(float(value)):
            found[name] = float(value)
    fps = getattr(transform, "fps", None)
    if fps:
        found["1/fps"] = 1e6 / float(fps)
    return found


def check_timing(
    t: np.ndarray, settings: Mapping[str, float] | None = None, *, source: str = "recording"
) -> bool:
    """Warn when timestamps in microseconds, or time settings, suggest a wrong time unit.

    Warns (:class:`TimeUnitWarning`) when the recording's ``N`` events span so little time
    that the rate ``N / span`` exceeds :data:`MAX_PLAUSIBLE_RATE` (with at least
    :data:`MIN_EVENTS_FOR_RATE` events), and when a setting is
    longer than the whole recording (so that one step, window or delay covers all of it).

    Args:
        t: ``(N,)`` timestamps in microseconds.
        settings: name -> value in microseconds (e.g. :func:`time_settings` of a transform,
            or ``{"window": 50_000}``).
        source: how the warning names the recording.

    Returns:
        ``True`` when it warned.

    Example:
        >>> import warnings
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     check_timing(np.linspace(0.0, 0.3, 3000), {"dt": 1000.0})
        True
        >>> "--time-unit" in str(caught[0].message)
        True
    """
    n = len(t)
    if n < 2:
        return False
    first, last = float(np.min(t)), float(np.max(t))
    span_us = last - first
    problems = []
    rate = math.inf if span_us <= 0 else n / (span_us / 1e6)
    if n >= MIN_EVENTS_FOR_RATE and rate > MAX_PLAUSIBLE_RATE:
        problems.append(f"{n} events in {span_us:g} us imply {rate:.3g} events/s, more than "
                        f"any sensor makes ({MAX_PLAUSIBLE_RATE:g})")
    longer = {k: v for k, v in (settings or {}).items() if span_us > 0 and v > span_us}
    if longer:
        listed = ", ".join(f"{k}={v:g} us" for k, v in longer.items())
        problems.append(f"{listed} exceed{'s' if len(longer) == 1 else ''} the whole "
                        f"recording ({span_us:g} us)")
    if not problems:
        return False
    warnings.warn(
        f"{source}: {'; '.join(problems)}. Timestamps are read as microseconds: if the file "
        "holds seconds, milliseconds or nanoseconds, say so (--time-unit s, or "
        "evdown_torch.time_units.to_microseconds); else choose shorter time settings",
        TimeUnitWarning,
        stacklevel=2,
    )
    return True
