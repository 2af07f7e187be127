"""Time units: conversion to microseconds and the warnings that catch a wrong unit."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from evdown_torch import (
    CubicEstimation,
    DensitySubsampling,
    LIFPooling,
    PhotocurrentPooling,
    PoissonSubsampling,
)
from evdown_torch.time_units import (
    TimeUnitWarning,
    check_timing,
    check_unit_name,
    display_unit,
    time_settings,
    to_microseconds,
)
from tests.helpers import DVS_DTYPE

FLOAT_DTYPE = np.dtype([("t", "<f4"), ("x", "<i2"), ("y", "<i2"), ("p", "<i1")])


def _stream(t, dtype=DVS_DTYPE) -> np.ndarray:
    out = np.zeros(len(t), dtype)
    out["t"] = t
    out["x"] = np.arange(len(t)) % 3
    return out


@pytest.mark.parametrize(("unit", "t", "expected", "dtype"), [
    ("s", [0, 2], [0, 2_000_000], np.int64),
    ("ms", [7, 9], [7000, 9000], np.int64),
    ("us", [7, 9], [7, 9], np.int64),
    ("ns", [1500, 2000], [1.5, 2.0], np.float64),
])
def test_integer_times_convert_exactly(unit, t, expected, dtype):
    events = _stream(t)
    out = to_microseconds(events, unit)
    assert out["t"].tolist() == expected and out["t"].dtype == dtype
    assert out.dtype.names == events.dtype.names and out["x"].tolist() == events["x"].tolist()
    assert events["t"].tolist() == t  # the input is not modified


def test_float_times_become_float64_microseconds_in_the_same_field_order():
    events = _stream([0.25, 0.5], FLOAT_DTYPE)
    out = to_microseconds(events, "s")
    assert out.dtype.names == ("t", "x", "y", "p") and out["t"].dtype == np.float64
    assert out["t"].tolist() == [250_000.0, 500_000.0] and out["p"].dtype == np.int8


def test_bad_units_and_overflow_are_refused():
    with pytest.raises(ValueError, match="time unit must be one of s, ms, us, ns, got 'sec'"):
        check_unit_name("sec")
    with pytest.raises(ValueError, match="overflow int64"):
        to_microseconds(_stream([2**62]), "s")


def test_display_unit_seconds_from_one_second():
    assert display_unit(999_999) == ("ms", 1e3) and display_unit(1e6) == ("s", 1e6)


def test_time_settings_of_transforms():
    sensor = (8, 8, 2)
    assert time_settings(LIFPooling(sensor, 2, dt=500, tau=float("inf"))) == {"dt": 500.0}
    assert time_settings(CubicEstimation(sensor, 2, max_delay=300)) == {"max_delay": 300.0}
    assert time_settings(CubicEstimation(sensor, 2)) == {}
    assert time_settings(PhotocurrentPooling(sensor, 2, fps=100)) == {"1/fps": 10_000.0}
    assert time_settings(PoissonSubsampling(sensor, 2, window=6000)) == {"window": 6000.0}
    assert time_settings(DensitySubsampling(sensor, 2, tau=2e4)) == {"tau": 20_000.0}


def _warned(t, settings=None) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        said = check_timing(np.asarray(t), settings, source="rec.npy")
    messages = [str(w.message) for w in caught if w.category is TimeUnitWarning]
    assert said == bool(messages)
    return messages


def test_an_implausible_rate_warns():
    seconds = np.linspace(0.0, 0.3, 2878)  # float seconds read as microseconds: 1e10 ev/s
    (message,) = _warned(seconds)
    assert message.startswith("rec.npy: 2878 events in 0.3 us") and "--time-unit s" in message
    assert not _warned(seconds * 1e6)  # the same in microseconds: 9.6 k events/s
    assert not _warned(np.zeros(99))  # too few events to tell (a burst at one timestamp)
    assert _warned(np.zeros(100))


def test_settings_longer_than_the_recording_warn():
    t = np.arange(0, 5000, 10)  # 4.99 ms
    (message,) = _warned(t, {"dt": 1000.0, "tau": 10_000.0, "window": 50_000.0})
    assert "tau=10000 us, window=50000 us exceed the whole recording (4990 us)" in message
    assert "dt=" not in message
    assert not _warned(t, {"dt": 4990.0})
    assert not _warned([5], {"dt": 1e9})  # one event spans no time: nothing to compare
