"""One time convention: time settings in the stream's unit, rates through ``time_unit``."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from evdown_torch import LIFPooling, PhotocurrentPooling
from evdown_torch.checks import check_time_unit
from evdown_torch.transforms import calibrate_weight
from evdown_torch.transforms.calibrate import BudgetTarget
from tests.helpers import photocurrent_frames_reference, random_stream, rows

SENSOR = (10, 7, 2)


@pytest.mark.parametrize("cutoff_hz", [0.0, 5.0])
def test_frames_mode_on_millisecond_timestamps_matches_the_reference(cutoff_hz, rng):
    # 400 ms at 50 fps: a frame every 20 ticks of 1 ms (at the default 1e-6 it would be
    # every 20,000 ticks, one frame for the whole stream).
    arr = random_stream(rng, 250, SENSOR, t_max=400)
    pool = PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, threshold=0.1, fps=50.0,
                               cutoff_hz=cutoff_hz, time_unit=1e-3)
    expected = photocurrent_frames_reference(arr, SENSOR, 2, 0.3, 0.1, 50.0, cutoff_hz,
                                             ticks_per_second=1000)
    assert len(expected) > 20
    assert sorted(rows(pool(arr))) == expected
    microseconds = PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, threshold=0.1,
                                       fps=50.0, cutoff_hz=cutoff_hz)
    assert sorted(rows(microseconds(arr))) != expected  # the unit matters


def test_float_seconds_give_the_microsecond_result_scaled(rng):
    # The same stream with float timestamps in microseconds and in seconds (time_unit 1.0):
    # the same events, at the same instants.
    n = 400
    arr = random_stream(rng, n, SENSOR).astype(
        [("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
    arr["t"] = np.sort(rng.uniform(0.0, 300_000.0, n))  # no event on a frame boundary
    seconds = arr.copy()
    seconds["t"] = arr["t"] * 1e-6
    settings = dict(factor=2, contrast=0.3, threshold=0.1, fps=200.0)
    in_us = PhotocurrentPooling(SENSOR, **settings)(arr)
    in_s = PhotocurrentPooling(SENSOR, time_unit=1.0, **settings)(seconds)
    assert len(in_us) > 30 and len(in_s) == len(in_us)
    for name in ("x", "y", "p"):
        np.testing.assert_array_equal(in_s[name], in_us[name])
    np.testing.assert_allclose(in_s["t"] * 1e6, in_us["t"], rtol=1e-9, atol=1e-6)


def test_time_unit_is_normalised_and_kept_with_the_frames_mode():
    pool = PhotocurrentPooling(SENSOR, fps=30, time_unit=1)
    assert pool.time_unit == 1.0 and type(pool.time_unit) is float
    assert PhotocurrentPooling(SENSOR, fps=30, time_unit="ms").time_unit == 1e-3
    default = PhotocurrentPooling(SENSOR, fps=30)
    assert default.time_unit is None and default.settings.time_unit == 1e-6  # as given
    assert PhotocurrentPooling(SENSOR).time_unit is None


def test_a_time_unit_left_out_stays_out_of_copies():
    # The field keeps what was given (None), not the default filled in for the kernels, so a
    # copy without the rate that needs it is valid, and a copy with another rate still
    # converts it at the default.
    frames = PhotocurrentPooling(SENSOR, 2, fps=1000.0)
    events_mode = dataclasses.replace(frames, fps=None)
    assert events_mode.time_unit is None and events_mode.fps is None
    assert dataclasses.replace(events_mode, fps=50.0).settings.time_unit == 1e-6
    given = PhotocurrentPooling(SENSOR, 2, fps=1000.0, time_unit=1e-6)  # given: kept, refused
    with pytest.raises(ValueError, match="time_unit=1e-06 converts the frames mode's fps"):
        dataclasses.replace(given, fps=None)
    rate = BudgetTarget.rate(100.0)
    assert rate.time_unit is None
    assert dataclasses.replace(rate, kind="ratio", value=0.1) == BudgetTarget.ratio(0.1)
    assert rate.events(input_events=10, duration=2e6) == 200.0  # the default, microseconds
    with pytest.raises(ValueError, match="time_unit=1e-06 applies only to a rate or peak target"):
        dataclasses.replace(BudgetTarget.rate(100.0, 1e-6), kind="count")


@pytest.mark.parametrize(("time_unit", "error", "message"), [
    (0.0, ValueError, "time_unit must be a positive"),
    (-1e-6, ValueError, "time_unit must be a positive"),
    (math.nan, ValueError, "time_unit must be a positive"),
    (math.inf, ValueError, "time_unit must be a positive"),
    (1e-13, ValueError, "at least 1e-12"),
    ("micro", ValueError, "time unit must be one of s, ms, us, ns"),
    (True, TypeError, "time_unit must be a positive number"),
])
def test_bad_time_units_are_refused_everywhere_with_one_message(time_unit, error, message):
    with pytest.raises(error, match=message):
        check_time_unit(time_unit)
    with pytest.raises(error, match=message):
        PhotocurrentPooling(SENSOR, fps=100.0, time_unit=time_unit)
    with pytest.raises(error, match=message):
        BudgetTarget.rate(100.0, time_unit)


def test_time_unit_is_refused_where_no_rate_uses_it(rng):
    with pytest.raises(ValueError, match="time_unit=0.001 converts the frames mode"):
        PhotocurrentPooling(SENSOR, time_unit=1e-3)
    with pytest.raises(ValueError, match="applies only to a rate or peak target"):
        BudgetTarget("ratio", 0.5, 1e-3)
    with pytest.raises(ValueError, match="applies only to a rate or peak target"):
        BudgetTarget("count", 100, 1.0)
    arr = random_stream(rng, 500, (8, 8, 2))
    with pytest.raises(ValueError, match="applies only to a rate or peak target"):
        calibrate_weight(arr, (8, 8, 2), 2, target_ratio=0.1, time_unit=1e-3)


def test_budget_rates_convert_through_time_unit():
    # 2e6 ticks: 2 s of microseconds, 2000 s of milliseconds.
    assert BudgetTarget.rate(300.0).events(input_events=1, duration=2e6) == 600.0
    assert BudgetTarget.rate(300.0, 1e-3).events(input_events=1, duration=2e6) == 600_000.0
    assert BudgetTarget.rate(300.0).time_unit is None  # as given: read as 1e-6


def test_calibrate_weight_reads_a_rate_in_the_given_unit(rng):
    # One stream, timestamps in milliseconds: 10 output events per second over 100 s is the
    # same count as 1e4 per second of a stream read in microseconds (1000 x shorter).
    sensor = (16, 16, 2)
    arr = random_stream(rng, 5000, sensor, t_max=100_000)
    span = int(arr["t"][-1] - arr["t"][0])
    kwargs = dict(dt=500, tau=3000.0)
    as_ms = calibrate_weight(arr, sensor, 4, target_rate=10.0, time_unit=1e-3, **kwargs)
    as_us = calibrate_weight(arr, sensor, 4, target_rate=1e4, **kwargs)
    assert as_ms == as_us
    got = len(LIFPooling(sensor, 4, weight=as_ms, **kwargs)(arr))
    assert abs(got - 10.0 * span * 1e-3) <= 0.05 * 10.0 * span * 1e-3


def test_the_readers_unit_names_are_accepted_as_seconds():
    assert [check_time_unit(name) for name in ("s", "ms", "us", "ns")] == [1.0, 1e-3, 1e-6, 1e-9]
    assert PhotocurrentPooling(SENSOR, fps=25, time_unit="s").time_unit == 1.0
    assert BudgetTarget.rate(10.0, "ms").time_unit == 1e-3
