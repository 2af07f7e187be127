"""Time units: conversion to microseconds and the warnings that catch a wrong unit."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from evdown_torch import (
    CubicEstimation,
    DensitySubsampling,
    LIFPooling,
    LinearEstimation,
    PhotocurrentPooling,
    PoissonSubsampling,
)
from evdown_torch.io import read_events, write_events
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


def _caught(t, settings=None) -> list[TimeUnitWarning]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        said = check_timing(np.asarray(t), settings, source="rec.npy")
    found = [w.message for w in caught if w.category is TimeUnitWarning]
    assert said == bool(found)
    return found


def _warned(t, settings=None) -> list[str]:
    return [str(w) for w in _caught(t, settings)]


def test_an_implausible_rate_warns_in_python_words_with_the_command_lines_beside():
    seconds = np.linspace(0.0, 0.3, 2878)  # float seconds read as microseconds: 1e10 ev/s
    (warning,) = _caught(seconds)
    message = str(warning)
    assert message.startswith("rec.npy: 2878 events in 0.3 us")
    assert "to_microseconds(events, 's')" in message and "read_events(path, time_unit='s')" in (
        message) and "--" not in message  # a Python caller is told Python
    assert warning.command_line.startswith("rec.npy: 2878 events in 0.3 us")
    assert "--time-unit s" in warning.command_line  # what evdown prints
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


# ----------------------------------------------------------------------------- everywhere


def _seconds_recording(rng, n=3000) -> np.ndarray:
    """An N-Caltech101-like recording in float seconds: 0.3 s, 3000 events, 24x18 pixels."""
    out = np.zeros(n, FLOAT64_DTYPE)
    out["t"] = np.sort(rng.uniform(0.0, 0.3, n))
    out["x"], out["y"] = rng.integers(0, 24, n), rng.integers(0, 18, n)
    out["p"] = rng.random(n) < 0.5
    return out


FLOAT64_DTYPE = np.dtype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<f8")])


def _time_unit_warnings(call) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        call()
    return [str(w.message) for w in caught if w.category is TimeUnitWarning]


def test_read_events_takes_a_time_unit_and_checks_an_unstated_one(tmp_path, rng):
    seconds = _seconds_recording(rng)
    path = tmp_path / "ncal.npy"
    np.save(path, seconds)
    recording = read_events(path, sensor_size=(24, 18, 2), time_unit="s")
    assert recording.time_unit == "us" and recording.events["t"].dtype == np.float64
    np.testing.assert_array_equal(recording.events["t"], seconds["t"] * 1e6)
    (message,) = _time_unit_warnings(lambda: read_events(path, sensor_size=(24, 18, 2)))
    assert str(path) in message and "read_events(path, time_unit='s')" in message
    assert not _time_unit_warnings(lambda: read_events(path, sensor_size=(24, 18, 2),
                                                       time_unit="s"))
    assert not _time_unit_warnings(lambda: read_events(path, sensor_size=(24, 18, 2),
                                                       time_unit="us"))  # said so: trusted
    write_events(tmp_path / "stated.npy", seconds, time_unit="s")  # the file's own unit wins
    stated = read_events(tmp_path / "stated.npy", sensor_size=(24, 18, 2), time_unit="ms")
    np.testing.assert_array_equal(stated.events["t"], seconds["t"] * 1e6)
    with pytest.raises(ValueError, match="time unit must be one of s, ms, us, ns, got 'sec'"):
        read_events(path, sensor_size=(24, 18, 2), time_unit="sec")


@pytest.mark.parametrize("make", [
    lambda: LIFPooling((24, 18, 2), 4),
    lambda: LinearEstimation((24, 18, 2), 4, max_delay=1000),
])
def test_a_transform_warns_once_at_its_first_call_on_seconds(make, rng):
    seconds = _seconds_recording(rng)
    transform = make()
    before = repr(transform)
    (message,) = _time_unit_warnings(lambda: transform(seconds))
    assert message.startswith(type(transform).__name__) and "to_microseconds" in message
    assert not _time_unit_warnings(lambda: transform(seconds))  # once per transform
    assert not _time_unit_warnings(lambda: transform.batch([seconds, seconds]))
    assert repr(transform) == before  # the frozen transform itself is not written to
    assert len(_time_unit_warnings(lambda: make().batch([seconds[:50], seconds]))) == 1
    session = make().session()  # a chunk is not a recording: sessions do not check
    assert not _time_unit_warnings(lambda: [session(c) for c in np.array_split(seconds, 3)])


def test_a_transform_checks_its_first_recording_of_enough_events_only(rng):
    transform = LIFPooling((24, 18, 2), 4)
    micro = to_microseconds(_seconds_recording(rng), "s")
    assert not _time_unit_warnings(lambda: transform(_seconds_recording(rng, 99)))  # too few
    assert not _time_unit_warnings(lambda: transform(micro))  # checked: plausible
    assert not _time_unit_warnings(lambda: transform(_seconds_recording(rng)))  # not again
    assert not _time_unit_warnings(lambda: LIFPooling((24, 18, 2), 4)(micro))
