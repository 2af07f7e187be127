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
    "check_choice",
    "check_factor",
    "check_has_values",
    "check_non_negative_float",
    "check_non_negative_int",
    "check_positive_float",
    "check_positive_int",
    "check_sensor_size",
    "check_time_constant",
    "check_unit_interval",
    "output_size",
]


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


def check_non_negative_int(name: str, value: Any) -> int:
    """Validate an integer ``>= 0`` and return it as an int."""
    if not _is_int(value):
        raise TypeError(f"{name} must be a non-negative integer, got {value!r}")
    if value < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


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
