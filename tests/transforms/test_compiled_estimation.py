"""LinearEstimation's compiled window against the eager driver and the exact reference."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

from evdown_torch import Events, LinearEstimation, eager_kernels, max_output_events
from evdown_torch.transforms.functional.estimation import driver
from evdown_torch.transforms.functional.estimation.method import linear_estimation
from tests.helpers import (
    FLOAT_DTYPE,
    assert_batches_on_both_paths,
    assert_identical,
    assert_matches_reference,
    assert_sessions_on_both_paths,
    both_paths,
    exact_linear_reference,
    near_their_limits,
    random_stream,
    spy,
    unique_pixel_times,
)

pytest.importorskip("numba")

SENSOR = (10, 7, 2)
FACTORS = [1, 2, 3, (2, 3), (3, 1), (4, 3), (10, 7)]  # (3, 1), (4, 3): not dividing
THRESHOLDS = [0.05, 0.123457, 0.3, 1.0, 2.5, 100.0]


@pytest.mark.parametrize("factor", FACTORS)
@pytest.mark.parametrize("threshold", THRESHOLDS)
@pytest.mark.parametrize("max_delay", [None, 4])
def test_compiled_equals_eager(factor, threshold, max_delay, rng):
    arr = random_stream(rng, 900, SENSOR, t_max=250, sort=False)
    transform = LinearEstimation(SENSOR, factor=factor, threshold=threshold, max_delay=max_delay)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)


@pytest.mark.parametrize("factor", [(1, 1), (2, 2), (4, 3)])
def test_compiled_matches_the_exact_reference(factor, rng):
    arr = unique_pixel_times(random_stream(rng, 300, SENSOR, t_max=2000))
    with eager_kernels(False):
        out = LinearEstimation(SENSOR, factor=factor, threshold=0.3)(arr)
    assert_matches_reference(out, exact_linear_reference(arr, SENSOR, factor, 0.3), True)


def test_the_compiled_window_runs_and_the_eager_solver_does_not(monkeypatch, rng):
    compiled_module = importlib.import_module("evdown_torch.transforms.functional.compiled."
                                              "linear")
    compiled_calls = spy(monkeypatch, compiled_module, "_linear_loop")
    eager_calls = spy(monkeypatch, driver, "pixel_knots")
    arr = random_stream(rng, 100, SENSOR)
    LinearEstimation(SENSOR, factor=2, threshold=0.5)(arr)
    assert (len(compiled_calls), len(eager_calls)) == (1, 0)
    with eager_kernels():
        LinearEstimation(SENSOR, factor=2, threshold=0.5)(arr)
    assert (len(compiled_calls), len(eager_calls)) == (1, 1)


@pytest.mark.parametrize("dtype", [np.int64, np.float32, np.float64])
@pytest.mark.parametrize("max_delay", [None, 3])
def test_timestamp_dtypes_near_their_limits(dtype, max_delay, rng):
    arr = random_stream(rng, 800, SENSOR, t_max=50, sort=False)
    data = near_their_limits(arr, dtype, 50)  # int64 up to 2**63 - 11
    transform = LinearEstimation(SENSOR, factor=(3, 2), threshold=0.25, max_delay=max_delay)
    compiled, eager = both_paths(lambda: transform(data))
    assert_identical(compiled, eager)
    assert len(compiled) > 0


def test_float64_timestamps_in_seconds(rng):
    arr = random_stream(rng, 600, SENSOR, t_max=200, dtype=FLOAT_DTYPE, sort=False)
    arr["t"] = arr["t"] * 1e-6 + 1.7e9  # seconds since 1970: pieces of a few ulps
    for max_delay in (None, 3e-6):
        transform = LinearEstimation(SENSOR, factor=2, threshold=0.3, max_delay=max_delay)
        compiled, eager = both_paths(lambda transform=transform: transform(arr))
        assert_identical(compiled, eager)


@pytest.mark.parametrize("threshold", [0.05, 0.3, 2.5])
@pytest.mark.parametrize("max_delay", [1, 7, 10**6])
def test_sessions_in_odd_chunks_and_moving_between_paths(threshold, max_delay, rng):
    arr = random_stream(rng, 1500, SENSOR, t_max=600)
    transform = LinearEstimation(SENSOR, factor=(3, 2), threshold=threshold,
                                 max_delay=max_delay)
    whole, eager_whole = both_paths(lambda: transform(arr))
    assert_identical(whole, eager_whole)
    assert_sessions_on_both_paths(transform, arr, whole)


def test_batches_sorted_stacked_and_with_empty_recordings(rng):
    transform = LinearEstimation(SENSOR, factor=(3, 2), threshold=0.2)

    def check(recording, out):  # each recording as if alone, on the eager path
        with eager_kernels():
            assert_identical(out, transform(recording))

    assert_batches_on_both_paths(transform, rng, SENSOR, 100, check)


def test_one_event_and_a_stream_at_one_time():
    one = Events.from_columns([3], [2], [7], [True])  # the region's mean +1/4: one ON
    cancelled = Events.from_columns([0, 1, 1, 0], [0, 0, 0, 1], [5, 5, 5, 5],
                                    [True, True, False, False])  # levels +1, 0, -1: mean 0
    for events, times in ((one, [7]), (cancelled, [])):
        compiled, eager = both_paths(lambda events=events: linear_estimation(
            events, sensor_size=SENSOR, factor=(2, 2), threshold=0.25))
        assert_identical(compiled, eager)
        assert compiled.t.tolist() == times


def test_hand_computed_ramp():
    # Two pixels of one region: the mean rises 0 -> 1/2 -> 1 over [0, 10] (levels 0.25 apart).
    events = Events.from_columns([0, 1], [0, 0], [0, 10], [1, 1])
    with eager_kernels(False):
        out = linear_estimation(events, sensor_size=(2, 1, 2), factor=(2, 1), threshold=0.25)
    assert out.t.tolist() == [0, 0, 5, 10] and out.p.tolist() == [True] * 4


@pytest.mark.parametrize("limit", [1, 37, 500])
def test_the_output_limit_raises_the_same_error_in_small_region_chunks(limit, monkeypatch, rng):
    monkeypatch.setattr(driver, "REGION_CHUNK_EVENTS", 64)  # many chunks, as on a big window
    arr = random_stream(rng, 700, SENSOR, t_max=300)
    transform = LinearEstimation(SENSOR, factor=1, threshold=0.05)
    messages = []
    for eager in (False, True):
        with eager_kernels(eager), max_output_events(limit), pytest.raises(ValueError) as error:
            transform(arr)
        messages.append(str(error.value))
    assert messages[0] == messages[1] and "more than the limit" in messages[0]
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)


def test_an_event_outside_the_sensor_is_an_error_not_a_crash():
    for x in (12, -3):
        events = Events.from_columns([0, x], [0, 1], [1, 2], [True, True])
        with eager_kernels(False), pytest.raises(ValueError, match=r"event 1 at \(x=.*lies "
                                                                      "outside the sensor"):
            linear_estimation(events, sensor_size=SENSOR, factor=(3, 2), threshold=0.5)


def test_the_input_is_not_written(rng):
    arr = random_stream(rng, 400, SENSOR, t_max=100)
    events = Events.from_columns(*(torch.as_tensor(arr[c].astype(np.int64))
                                   for c in ("x", "y", "t")), torch.as_tensor(arr["p"]))
    before = [column.clone() for column in events]
    with eager_kernels(False):
        linear_estimation(events, sensor_size=SENSOR, factor=2, threshold=0.1, max_delay=5)
    assert_identical(list(events), before)
