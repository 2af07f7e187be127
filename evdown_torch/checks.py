"""Validation of user-facing settings, in one place.

Every public entry point validates its settings here, so that a bad value raises the same
`ValueError`/`TypeError` with a message that names what was expected and what came.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch

__all__ = [
    "DEFAULT_MAX_OUTPUT_EVENTS",
    "MAX_EXACT_SPAN",
    "check_choice",
    "check_factor",
    "check_has_values",
    "check_item_index",
    "check_non_negative_float",
    "check_non_negative_int",
    "check_output_count",
    "check_positive_float",
    "check_positive_int",
    "check_sensor_size",
    "check_time_constant",
    "check_time_span",
    "check_unit_interval",
    "max_output_events",
    "output_size",
    "set_max_output_events",
]

#: Default most events one call of a downscaler may emit (see :func:`set_max_output_events`).
#: 100 million events are about 2.5 GB as tensors, and a kernel needs several times that
#: while it builds them; thresholds far below a region's level steps can ask for much more.
DEFAULT_MAX_OUTPUT_EVENTS = 100_000_000

_max_output_events = DEFAULT_MAX_OUTPUT_EVENTS

#: Spans ``t_end - t_start`` of integer timestamps the estimators refuse from (2**53, about
#: 285 years in microseconds): crossing times are float64 offsets from the pieces' starts,
#: which stop holding every integer there (below it, a time is within 1e-12 of its piece's
#: length of the exact one, and shifting the clock shifts it exactly).
MAX_EXACT_SPAN = 2**53


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


def check_positive_float(name: str, value: Any) -> float:
    """Validate a finite, strictly positive real number and return it as a float."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise TypeError(f"{name} must be a positive number, got {value!r}")
    value = float(value)
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


def check_non_negative_float(name: str, value: Any) -> float:
    """Validate a finite real number ``>= 0`` and return it as a float."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise TypeError(f"{name} must be a non-negative number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a non-negative finite number, got {value!r}")
    return value


def check_unit_interval(name: str, value: Any) -> float:
    """Validate a real number in ``[0, 1]`` (a decay factor) and return it as a float."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise TypeError(f"{name} must be a number in [0, 1], got {value!r}")
    value = float(value)
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
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise TypeError(f"{name} must be a positive number (math.inf for no leak), got {value!r}")
    value = float(value)
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


def max_output_events() -> int:
    """The most events one call of a downscaler may emit (see :func:`set_max_output_events`)."""
    return _max_output_events


def set_max_output_events(limit: int | None) -> int:
    """Set the most events one call of a downscaler may emit; returns the previous limit.

    The log-luminance methods (EventCount, LinearEstimation, CubicEstimation) can emit many
    events per input event when the threshold is small; they count their output before
    building it and raise a ``ValueError`` naming the count when it exceeds this limit, instead
    of running out of memory. The limit holds for the whole process.

    Args:
        limit: a positive number of events, or ``None`` for
            :data:`DEFAULT_MAX_OUTPUT_EVENTS` (100 million).

    Returns:
        The limit that was in force before.

    Example:
        >>> previous = set_max_output_events(10**9)
        >>> max_output_events()
        1000000000
        >>> set_max_output_events(previous) == 10**9
        True
    """
    global _max_output_events
    previous = _max_output_events
    _max_output_events = (
        DEFAULT_MAX_OUTPUT_EVENTS if limit is None else check_positive_int("limit", limit)
    )
    return previous


def check_output_count(count: int) -> None:
    """Refuse an output of ``count`` events above :func:`max_output_events`."""
    if count > _max_output_events:
        raise ValueError(
            f"the output would hold at least {count:,} events, more than the limit of "
            f"{_max_output_events:,}; a larger threshold or factor gives fewer events, and "
            "evdown_torch.set_max_output_events(n) raises the limit"
        )


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
