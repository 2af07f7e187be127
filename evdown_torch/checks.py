"""Validation of user-facing settings, in one place.

Every public entry point validates its settings here, so that a bad value raises the same
`ValueError`/`TypeError` with a message that names what was expected and what came.
"""

from __future__ import annotations

import math
import numbers
import os
import warnings
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from contextvars import ContextVar
from fractions import Fraction
from typing import Any

import torch

from evdown_torch.time_units import TIME_UNITS, check_unit_name

__all__ = [
    "DEFAULT_MAX_OUTPUT_EVENTS",
    "DEFAULT_TIME_UNIT",
    "MAX_EXACT_SPAN",
    "OutputLimitError",
    "check_choice",
    "check_factor",
    "check_finite_number",
    "check_has_values",
    "check_item_index",
    "check_non_negative_float",
    "check_non_negative_int",
    "check_output_count",
    "check_positive_float",
    "check_positive_int",
    "check_sensor_size",
    "check_state_memory",
    "check_time_constant",
    "check_time_span",
    "check_time_unit",
    "check_unit_interval",
    "device_memory",
    "max_output_events",
    "output_limit",
    "output_size",
    "set_max_output_events",
    "swapped_sensor_hint",
    "time_unit_fraction",
]

#: Default most events one call of a downscaler may emit (see :func:`max_output_events`).
#: 100 million events are about 2.5 GB as tensors, and a kernel needs several times that
#: while it builds them; thresholds far below a region's level steps can ask for much more.
DEFAULT_MAX_OUTPUT_EVENTS = 100_000_000

#: The output limit of the current thread (or asyncio task): a context variable, so a limit
#: set in one thread never applies to another.
_OUTPUT_LIMIT: ContextVar[int | None] = ContextVar(
    "evdown_torch_max_output_events", default=DEFAULT_MAX_OUTPUT_EVENTS
)

#: Seconds per timestamp unit where nothing else is said: microseconds, as Tonic's datasets.
DEFAULT_TIME_UNIT = 1e-6

#: Largest denominator of the fraction a ``time_unit`` is read as (so 1e-6 is exactly
#: 1/10**6 and 1e-9 exactly 1/10**9); a time unit must be at least its inverse (1e-12 s).
MAX_TIME_UNIT_DENOMINATOR = 10**12

#: The share of a device's memory that a method's dense per-pixel state may take: the kernels
#: need room besides it (a chunk's events and regions, the output).
STATE_MEMORY_SHARE = 0.25

#: Spans ``t_end - t_start`` of integer timestamps the estimators refuse from (2**53, about
#: 285 years in microseconds): crossing times are float64 offsets from the pieces' starts,
#: which stop holding every integer there (below it, a time is within 1e-12 of its piece's
#: length of the exact one, and shifting the clock shifts it exactly).
MAX_EXACT_SPAN = 2**53


class OutputLimitError(ValueError):
    """A call would emit (or compute) more than the output limit (:func:`max_output_events`)."""


def _is_int(value: Any) -> bool:
    """True for Python/NumPy integers, False for bools and everything else."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_sensor_size(sensor_size: Any) -> tuple[int, int, int]:
    """Validate a Tonic sensor size ``(W, H, P)`` and return it as a tuple of ints.

    Args:
        sensor_size: width, height and number of polarities (1 or 2).

    Returns:
        ``(W, H, P)`` as Python ints.

    Raises:
        TypeError: if it is not a sequence of three integers.
        ValueError: if a dimension is not positive or ``P`` is not 1 or 2.
    """
    try:
        items = tuple(sensor_size)
    except TypeError:
        raise TypeError(
            f"sensor_size must be a tuple (W, H, P) of integers, got {sensor_size!r}"
        ) from None
    if len(items) != 3 or not all(_is_int(v) for v in items):
        raise TypeError(f"sensor_size must be a tuple (W, H, P) of integers, got {sensor_size!r}")
    w, h, p = (int(v) for v in items)
    if w <= 0 or h <= 0:
        raise ValueError(f"sensor_size width and height must be positive, got {sensor_size!r}")
    if p not in (1, 2):
        raise ValueError(f"sensor_size polarity count P must be 1 or 2, got {sensor_size!r}")
    return w, h, p


def swapped_sensor_hint(extent: tuple[int, int], sensor_size: tuple[int, int, int]) -> str:
    """What an error about coordinates outside ``sensor_size`` adds when width and height swap.

    Args:
        extent: ``(largest x + 1, largest y + 1)`` of the events.
        sensor_size: the ``(W, H, P)`` they do not fit.

    Returns:
        ``""``, or a hint that the size is width first, when the events fit ``(H, W, P)``.

    Example:
        >>> swapped_sensor_hint((320, 240), (240, 320, 2))
        '; sensor sizes are width first, (W, H, P): (320, 240, 2)?'
    """
    w, h, p = sensor_size
    if extent[0] <= h and extent[1] <= w and not (extent[0] <= w and extent[1] <= h):
        return f"; sensor sizes are width first, (W, H, P): {(h, w, p)}?"
    return ""


def check_factor(factor: Any, sensor_size: tuple[int, int, int] | None = None) -> tuple[int, int]:
    """Validate a downscaling factor and return it as a pair ``(fx, fy)``.

    Args:
        factor: a positive integer, or a pair ``(fx, fy)`` of them.
        sensor_size: when given, each factor must not exceed the sensor's extent.

    Returns:
        ``(fx, fy)`` as Python ints.

    Raises:
        TypeError: if it is neither an integer nor a pair of integers.
        ValueError: if a factor is not positive or is larger than the sensor.
    """
    message = f"factor must be a positive integer or a pair of them, got {factor!r}"
    if _is_int(factor):
        pair = (int(factor), int(factor))
    elif isinstance(factor, (tuple, list)) and len(factor) == 2 and all(_is_int(v) for v in factor):
        pair = (int(factor[0]), int(factor[1]))
    elif isinstance(factor, numbers.Real) and not isinstance(factor, bool):
        raise ValueError(message)
    else:
        raise TypeError(message)
    if pair[0] <= 0 or pair[1] <= 0:
        raise ValueError(message)
    if sensor_size is not None and (pair[0] > sensor_size[0] or pair[1] > sensor_size[1]):
        raise ValueError(
            f"factor {factor!r} is larger than the sensor "
            f"({sensor_size[0]} x {sensor_size[1]} pixels)"
        )
    return pair


def output_size(
    sensor_size: tuple[int, int, int], factor: tuple[int, int]
) -> tuple[int, int, int]:
    """Output sensor size ``(ceil(W / fx), ceil(H / fy), P)``."""
    w, h, p = sensor_size
    return -(-w // factor[0]), -(-h // factor[1]), p


def _real(name: str, value: Any, wanted: str) -> float:
    """``value`` as a float if it is a real number (not a bool); a TypeError naming ``wanted``."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise TypeError(f"{name} must be {wanted}, got {value!r}")
    return float(value)


def check_positive_float(name: str, value: Any) -> float:
    """Validate a finite, strictly positive real number and return it as a float."""
    value = _real(name, value, "a positive number")
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return value


def check_positive_int(name: str, value: Any) -> int:
    """Validate a strictly positive integer and return it as an int."""
    if not _is_int(value):
        raise TypeError(f"{name} must be a positive integer, got {value!r}")
    if value <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def check_finite_number(name: str, value: Any) -> int | float:
    """Validate a finite real number (a time, a bound); integers stay exact Python ints.

    Raises:
        TypeError: for a bool or a non-number.
        ValueError: for NaN or an infinity.
    """
    if _is_int(value):
        return int(value)
    number = _real(name, value, "a finite number")
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number, got {number!r}")
    return number


def check_non_negative_float(name: str, value: Any) -> float:
    """Validate a finite real number ``>= 0`` and return it as a float."""
    value = _real(name, value, "a non-negative number")
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a non-negative finite number, got {value!r}")
    return value


def check_unit_interval(name: str, value: Any) -> float:
    """Validate a real number in ``[0, 1]`` (a decay factor) and return it as a float."""
    value = _real(name, value, "a number in [0, 1]")
    if not 0.0 <= value <= 1.0:  # also rejects NaN
        raise ValueError(f"{name} must lie in [0, 1], got {value!r}")
    return value


def check_choice(name: str, value: Any, choices: tuple[str, ...]) -> str:
    """Validate that ``value`` is one of the strings ``choices`` and return it."""
    if not isinstance(value, str):
        raise TypeError(f"{name} must be one of {list(choices)}, got {value!r}")
    if value not in choices:
        raise ValueError(f"{name} must be one of {list(choices)}, got {value!r}")
    return value


def check_time_constant(name: str, value: Any) -> float:
    """Validate a time constant: a positive number, ``math.inf`` allowed (no leak)."""
    value = _real(name, value, "a positive number (math.inf for no leak)")
    if not value > 0:  # also rejects NaN
        raise ValueError(f"{name} must be a positive number (math.inf for no leak), got {value!r}")
    return value


def check_item_index(index: Any, length: int, what: str = "items") -> int:
    """Validate a dataset index (negative counts from the end) and return it in ``[0, length)``.

    Raises:
        TypeError: if ``index`` is not an integer.
        IndexError: if it is outside ``[-length, length)``.

    Example:
        >>> check_item_index(-1, 5, "recordings")
        4
    """
    import operator

    try:
        index = operator.index(index)
    except TypeError:
        raise TypeError(f"index must be an integer, got {index!r}") from None
    if not -length <= index < length:
        raise IndexError(f"index {index} is out of range for {length} {what}")
    return index % length


def check_non_negative_int(name: str, value: Any) -> int:
    """Validate an integer ``>= 0`` and return it as an int."""
    if not _is_int(value):
        raise TypeError(f"{name} must be a non-negative integer, got {value!r}")
    if value < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


def output_limit() -> int | None:
    """The most events one call of a downscaler may emit here (``None``: no limit).

    The limit in force in the current thread (or asyncio task): :data:`DEFAULT_MAX_OUTPUT_EVENTS`
    unless a :func:`max_output_events` block around the call says otherwise.

    Example:
        >>> output_limit() == DEFAULT_MAX_OUTPUT_EVENTS
        True
    """
    return _OUTPUT_LIMIT.get()


def max_output_events(limit: int | None) -> AbstractContextManager[int | None]:
    """A block in which one call of a downscaler may emit at most ``limit`` events.

    Every transform counts its output and raises a ``ValueError`` naming the count when it
    exceeds the limit: no call emits more. The log-luminance methods (EventCount,
    LinearEstimation, CubicEstimation, PhotocurrentPooling), whose small thresholds can emit
    many events per input event, and LIFPooling, whose neurons can fire at every step of a
    long silence, count before they build anything, instead of running out of memory; the
    methods whose output is at most their input (Downsample, EventFunnelling,
    TemporalFunnelling, ThinnedDownsample) count what they built. The limit counts one call:
    one ``transform(events)``, one ``transform.batch(...)`` as a whole, one chunk of a
    session. Outside any block it is :data:`DEFAULT_MAX_OUTPUT_EVENTS` (100 million events,
    about 2.5 GB as tensors).

    The limit lives in a context variable: it holds for the calls made inside the ``with``
    block, in this thread (or asyncio task) only, and the previous limit comes back when the
    block ends, however it ends. Other threads, and DataLoader worker processes, keep their own
    limit (the default unless they open a block themselves). Blocks nest. The object is also a
    decorator (``@max_output_events(10**9)``).

    This replaces the process-wide ``set_max_output_events`` (deprecated) and the field
    ``LIFPooling.max_output_events`` (removed).

    Args:
        limit: a positive number of events, or ``None`` for no limit.

    Returns:
        A context manager; ``with max_output_events(n) as limit:`` binds the limit.

    Raises:
        TypeError, ValueError: for a limit that is neither a positive integer nor ``None``
            (at once, before the block).

    Example:
        >>> with max_output_events(10**9):
        ...     output_limit()
        1000000000
        >>> output_limit() == DEFAULT_MAX_OUTPUT_EVENTS
        True
    """
    if limit is not None:
        limit = check_positive_int("max_output_events", limit)
    return _output_limit_block(limit)


@contextmanager
def _output_limit_block(limit: int | None) -> Iterator[int | None]:
    token = _OUTPUT_LIMIT.set(limit)
    try:
        yield limit
    finally:
        _OUTPUT_LIMIT.reset(token)


def set_max_output_events(limit: int | None) -> int | None:
    """Deprecated: use ``with evdown_torch.max_output_events(n):`` around the calls.

    Sets the limit of the current thread (or asyncio task) until it is set again, no longer
    of the whole process; kept for one version.

    Args:
        limit: a positive number of events, or ``None`` for no limit (as
            :func:`max_output_events` takes it).

    Returns:
        The limit that was in force before (``None``: none), which this function takes back.
    """
    warnings.warn(
        "evdown_torch.set_max_output_events is deprecated and will be removed; use "
        "`with evdown_torch.max_output_events(n): ...` around the calls",
        DeprecationWarning,
        stacklevel=2,
    )
    previous = _OUTPUT_LIMIT.get()
    _OUTPUT_LIMIT.set(None if limit is None else check_positive_int("limit", limit))
    return previous


def check_output_count(
    count: int, *, detail: str = "", fewer: str = "a larger threshold or factor gives fewer events"
) -> None:
    """Refuse an output of ``count`` events above the limit in force (:func:`output_limit`).

    Args:
        count: how many events the call would emit (at least).
        detail: said after the count, e.g. where the events come from.
        fewer: how the method's settings give fewer events.

    Raises:
        OutputLimitError: naming the count and the limit, when ``count`` exceeds the limit.
    """
    limit = _OUTPUT_LIMIT.get()
    if limit is not None and count > limit:
        raise OutputLimitError(
            f"the output would hold at least {count:,} events{detail}, more than the limit of "
            f"{limit:,}; {fewer}, and `with evdown_torch.max_output_events(n):` around the "
            "call raises the limit (None: no limit)"
        )


def check_time_unit(time_unit: Any) -> float:
    """Validate a ``time_unit``: the seconds one timestamp unit lasts, for rates in hertz.

    A unit's name as the file readers take it (``"s"``, ``"ms"``, ``"us"``, ``"ns"``, see
    :data:`evdown_torch.time_units.TIME_UNITS`) is accepted too and turned into seconds.

    Every time setting of a method (``dt``, ``tau``, ``max_delay``, ...) is in the stream's
    own unit; only settings given per second (a frame rate, a cut-off frequency, a budget in
    events per second) need to know how long that unit is, and they all take it as
    ``time_unit`` (1e-6, the default, for microseconds; 1.0 for float seconds). It is read as
    the nearest fraction with a denominator of at most 10**12 (:func:`time_unit_fraction`),
    so 1e-6 and 1e-9 are exact.

    Returns:
        ``time_unit`` in seconds, as a float.

    Raises:
        TypeError: for a non-number that is not a unit's name.
        ValueError: for a value that is not finite, below 1e-12 (a picosecond), or an
            unknown name.

    Example:
        >>> check_time_unit(1e-3), check_time_unit("ms")
        (0.001, 0.001)
    """
    if isinstance(time_unit, str):
        return TIME_UNITS[check_unit_name(time_unit)] * 1e-6  # microseconds -> seconds
    value = check_positive_float("time_unit", time_unit)
    if value * MAX_TIME_UNIT_DENOMINATOR < 1:
        raise ValueError(
            f"time_unit (seconds per timestamp unit) must be at least 1e-12, got {time_unit!r}"
        )
    return value


def time_unit_fraction(time_unit: float) -> Fraction:
    """A validated ``time_unit`` as the exact fraction the frame clocks compute with.

    Example:
        >>> time_unit_fraction(1e-6)
        Fraction(1, 1000000)
    """
    return Fraction(time_unit).limit_denominator(MAX_TIME_UNIT_DENOMINATOR)


def check_time_span(t_start: int, t_end: int) -> None:
    """Refuse integer timestamps spanning :data:`MAX_EXACT_SPAN` or more (estimators)."""
    span = int(t_end) - int(t_start)
    if span >= MAX_EXACT_SPAN:
        raise ValueError(
            f"the events span {span:,} time units from first to last timestamp; the linear and "
            f"cubic estimators compute crossing times as float64 offsets, which hold spans "
            f"below 2**53 only ({MAX_EXACT_SPAN:,}, about 285 years in microseconds)"
        )


def check_has_values(tensor: torch.Tensor, what: str = "events") -> None:
    """Refuse tensors that hold no values: those on PyTorch's ``meta`` device.

    Raises:
        ValueError: for a tensor on the ``meta`` device.
    """
    if tensor.device.type == "meta":
        raise ValueError(
            f"{what} are on the 'meta' device, which holds shapes but no values; downscaling "
            "reads the values: move them to a real device first (e.g. .to('cpu'))"
        )


def device_memory(device: torch.device | str | None = None) -> int | None:
    """Bytes of memory of ``device`` (RAM for the CPU, the GPU's for CUDA); ``None``: unknown."""
    device = torch.device("cpu" if device is None else device)
    if device.type == "cuda":
        return int(torch.cuda.get_device_properties(device).total_memory)
    if device.type == "cpu":
        try:
            return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
        except (AttributeError, ValueError, OSError):
            return None
    return None


def check_state_memory(
    method: str,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    *,
    pixel_bytes: int = 0,
    region_bytes: int = 0,
    recordings: int = 1,
    device: torch.device | str | None = None,
) -> None:
    """Refuse a dense per-pixel state larger than :data:`STATE_MEMORY_SHARE` of the memory.

    The methods that keep a value for every pixel or region (EventCount, the estimators' and
    LIFPooling's sessions, PhotocurrentPooling) call this before they allocate it.

    Args:
        method: the method's name, for the message.
        sensor_size: ``(W, H, P)``.
        factor: ``(fx, fy)``.
        pixel_bytes: bytes of state per input pixel.
        region_bytes: bytes of state per output region.
        recordings: recordings whose states are stacked (a batch).
        device: where the state lives (:func:`device_memory`; unknown memory: no check).

    Raises:
        ValueError: naming the memory the state needs, the device's, and the largest sensor
            of this shape that fits.
    """
    w, h, _ = sensor_size
    out_w, out_h, _ = output_size(sensor_size, factor)
    need = recordings * (pixel_bytes * w * h + region_bytes * out_w * out_h)
    memory = device_memory(device)
    if memory is None or need <= memory * STATE_MEMORY_SHARE:
        return
    scale = math.sqrt(memory * STATE_MEMORY_SHARE / need)
    fit_w, fit_h = max(int(w * scale), 1), max(int(h * scale), 1)
    several = f" for {recordings} recordings" if recordings > 1 else ""
    raise ValueError(
        f"{method} keeps state for every pixel or region of its sensor: {w} x {h} pixels at "
        f"factor {factor} need {need / 1e9:.3g} GB{several}, more than a quarter of the "
        f"{memory / 1e9:.3g} GB of memory here ({torch.device(device or 'cpu')}); the largest "
        f"sensor of this shape that fits is about {fit_w} x {fit_h} pixels"
        + ("; or give fewer recordings per batch" if several else ""))
