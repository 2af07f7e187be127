"""Time units of event files, and the checks that catch a wrong one.

Kernels read timestamps in "the stream's time unit", and every default of the package (LIF's
``dt`` = 1 ms, ``tau`` = 10 ms, ``evdown show``'s 50 ms windows) assumes microseconds, the
unit of Tonic's datasets and of AEDAT4, N-MNIST and Prophesee files. Files in other units
(float seconds, as some N-Caltech101 conversions and several tools write them; nanoseconds)
are converted once, at the edge, with :func:`to_microseconds`.

A wrong unit shows itself in two ways that :func:`check_timing` warns about (a
:class:`TimeUnitWarning`): an implied event rate over :data:`MAX_PLAUSIBLE_RATE` (float seconds
read as microseconds put a whole recording inside a few microseconds), and a time setting
(``dt``, ``tau``, ``max_delay``, a window) longer than the whole recording. It is the one check
of the package: :func:`~evdown_torch.io.read_events` makes it (the rate) on a file whose unit
nobody states, every transform at its first call (:func:`check_first_call`: the rate and its
own time settings, once per transform), and ``evdown`` on every file it reads.

:func:`display_unit` chooses seconds or milliseconds for showing times from a recording's start.
"""

from __future__ import annotations

import math
import warnings
import weakref
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

import numpy as np

from evdown_torch._text import WordedWarning

__all__ = [
    "MAX_PLAUSIBLE_RATE",
    "TIME_UNITS",
    "MIN_EVENTS_FOR_RATE",
    "TimeUnitWarning",
    "check_first_call",
    "check_unit_name",
    "check_timing",
    "display_unit",
    "time_settings",
    "timing_checked_by_caller",
    "timing_warning",
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


class TimeUnitWarning(WordedWarning):
    """Timestamps or time settings that look like the wrong time unit.

    Its text names the fix in Python; ``evdown`` prints its ``command_line`` wording
    (``--time-unit``) instead.
    """


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


def timing_warning(
    t: Any, settings: Mapping[str, float] | None = None, *, source: str = "recording"
) -> TimeUnitWarning | None:
    """The warning of :func:`check_timing`, made but not given; ``None`` when all looks right.

    Args:
        t: ``(N,)`` timestamps in microseconds (a NumPy array or a tensor).
        settings: name -> value in microseconds.
        source: how the warning names the recording.

    Example:
        >>> timing_warning(np.linspace(0.0, 0.3, 3000)).command_line[:45]
        'recording: 3000 events in 0.3 us imply 1e+10 '
        >>> timing_warning(np.linspace(0.0, 3e5, 3000)) is None
        True
    """
    n = len(t)
    if n < 2:
        return None
    first, last = float(t.min()), float(t.max())
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
        return None
    said = f"{source}: {'; '.join(problems)}. Timestamps are read as microseconds: if "
    return TimeUnitWarning(
        said + "they are seconds, milliseconds or nanoseconds, convert them first "
        "(evdown_torch.time_units.to_microseconds(events, 's'), or "
        "evdown_torch.io.read_events(path, time_unit='s')); else choose shorter time settings",
        said + "the file holds seconds, milliseconds or nanoseconds, say so (--time-unit s, "
        "ms or ns); else choose shorter time settings",
    )


def check_timing(
    t: Any, settings: Mapping[str, float] | None = None, *, source: str = "recording",
    transforms: Iterable[object] = (),
) -> bool:
    """Warn when timestamps in microseconds, or time settings, suggest a wrong time unit.

    Warns (:class:`TimeUnitWarning`) when the recording's ``N`` events span so little time
    that the rate ``N / span`` exceeds :data:`MAX_PLAUSIBLE_RATE` (with at least
    :data:`MIN_EVENTS_FOR_RATE` events), and when a setting is
    longer than the whole recording (so that one step, window or delay covers all of it).
    Silent inside :func:`timing_checked_by_caller`.

    Args:
        t: ``(N,)`` timestamps in microseconds (a NumPy array or a tensor).
        settings: name -> value in microseconds (e.g. :func:`time_settings` of a transform,
            or ``{"window": 50_000}``).
        source: how the warning names the recording.
        transforms: the transforms whose settings these are: the check stands for their first
            call's (:func:`check_first_call`), which is then not made again.

    Returns:
        ``True`` when it warned.

    Example:
        >>> import warnings
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     check_timing(np.linspace(0.0, 0.3, 3000), {"dt": 1000.0})
        True
        >>> "to_microseconds(events, 's')" in str(caught[0].message)
        True
    """
    for transform in transforms:
        _remember(transform)
    if _CHECKED_BY_CALLER.get():
        return False
    warning = timing_warning(t, settings, source=source)
    if warning is None:
        return False
    warnings.warn(warning, stacklevel=2)
    return True


#: ``id`` of each live transform whose timing was checked (:func:`check_first_call`). Kept
#: outside the transforms, which are frozen; an entry leaves with its transform.
_CHECKED: set[int] = set()


def _remember(transform: object) -> bool:
    """Note ``transform`` as checked; ``False`` if it was already."""
    key = id(transform)
    if key in _CHECKED:
        return False
    try:
        weakref.finalize(transform, _CHECKED.discard, key)
    except TypeError:  # not weakly referenceable: checked at every call instead
        return True
    _CHECKED.add(key)
    return True


def check_first_call(transform: object, t: Any) -> bool:
    """The timing check a transform makes on the first recording it is called on.

    :func:`check_timing` of the timestamps ``t`` (microseconds) against the transform's
    :func:`time_settings`, once per transform: the first recording of at least
    :data:`MIN_EVENTS_FOR_RATE` events is checked (fewer say nothing about the rate), later
    ones are not, so a transform warns at most once and costs nothing after. A caller that
    checks the recording itself (``evdown``, naming the file) passes the transform to
    :func:`check_timing` instead. Streaming sessions do not check: a chunk is not a recording.

    Args:
        transform: the transform (its object identity is what is remembered).
        t: ``(N,)`` timestamps of the recording, a tensor or NumPy array.

    Returns:
        ``True`` when it warned.
    """
    if len(t) < MIN_EVENTS_FOR_RATE or id(transform) in _CHECKED or _CHECKED_BY_CALLER.get():
        return False
    return check_timing(t, time_settings(transform), source=type(transform).__name__,
                        transforms=(transform,))


#: Whether the caller checks the timing itself (:func:`timing_checked_by_caller`): a context
#: variable, so that the block silences its own thread (or asyncio task) only.
_CHECKED_BY_CALLER: ContextVar[bool] = ContextVar("evdown_torch_timing_checked_by_caller",
                                                  default=False)


@contextmanager
def timing_checked_by_caller() -> Iterator[None]:
    """Silence the timing checks of readers and transforms inside the block, in this thread.

    For a caller that checks the recordings itself (:func:`timing_warning`,
    :func:`check_timing` outside the block), against every time setting and naming the file,
    so that the readers' check (the rate alone) or a transform's first call would not say it
    again: ``evdown``'s commands, and ``evdown preprocess``'s shards, which hand their first
    recording's warning to the run. Unlike ``warnings.catch_warnings``, it leaves other
    threads' warnings alone.
    """
    token = _CHECKED_BY_CALLER.set(True)
    try:
        yield
    finally:
        _CHECKED_BY_CALLER.reset(token)
