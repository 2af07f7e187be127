"""EventCount's compiled CPU loop against its eager kernel and the exact reference."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

from evdown_torch import EventCount, Events
from evdown_torch.transforms.functional.event_count import (
    EventCountState,
    event_count,
    event_count_init,
    event_count_step,
)
from tests.helpers import (
    DVS_DTYPE,
    FLOAT_DTYPE,
    assert_batches_on_both_paths,
    assert_compiled_then_eager,
    assert_identical,
    assert_output_limit_on_both_paths,
    assert_sessions_on_both_paths,
    both_paths,
    event_count_reference,
    near_their_limits,
    random_stream,
    rows,
)

pytest.importorskip("numba")

SENSOR = (10, 7, 2)
FACTORS = [1, 2, 3, 4, (2, 3), (3, 1), (4, 3), (10, 7)]  # (3, 1), (4, 3): not dividing
THRESHOLDS = [0.05, 0.123457, 0.3, 1.0, 2.5, 100.0]


@pytest.mark.parametrize("factor", FACTORS)
@pytest.mark.parametrize("threshold", THRESHOLDS)
def test_compiled_equals_eager_and_the_reference(factor, threshold, rng):
    arr = random_stream(rng, 1200, SENSOR, t_max=300, sort=False)
    transform = EventCount(SENSOR, factor=factor, threshold=threshold)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert rows(compiled) == event_count_reference(arr, SENSOR, factor, threshold)


def test_the_compiled_loop_runs_and_the_eager_kernel_does_not(monkeypatch, rng):
    compiled_module = importlib.import_module("evdown_torch.transforms.functional.compiled."
                                              "event_count")
    eager_module = importlib.import_module("evdown_torch.transforms.functional.event_count")
    arr = random_stream(rng, 100, SENSOR)
    assert_compiled_then_eager(monkeypatch, (compiled_module, "event_count_step"),
                               (eager_module, "_event_count_sorted"),
                               lambda: EventCount(SENSOR, factor=2, threshold=0.5)(arr))


@pytest.mark.parametrize("dtype", [np.int64, np.float32, np.float64])
def test_timestamp_dtypes_near_their_limits(dtype, rng):
    arr = random_stream(rng, 800, SENSOR, t_max=50, sort=False)
    data = near_their_limits(arr, dtype, 50)  # int64 up to 2**63 - 11
    transform = EventCount(SENSOR, factor=(3, 2), threshold=0.25)
    compiled, eager = both_paths(lambda: transform(data))
    assert_identical(compiled, eager)
    assert compiled.dtype == data.dtype and len(compiled) > 0
    if dtype == np.int64:
        assert int(compiled[:, 2].min()) >= 2**63 - 60
        expected = event_count_reference(arr, SENSOR, (3, 2), 0.25)
        assert [tuple(r) for r in compiled[:, [0, 1, 3]].tolist()] == [
            (x, y, 1 if on else -1) for x, y, _, on in expected]


def test_float64_structured_timestamps(rng):
    arr = random_stream(rng, 600, SENSOR, t_max=200, dtype=FLOAT_DTYPE, sort=False)
    arr["t"] = arr["t"] * 1e-6 + 1.7e9  # seconds since 1970, in float64
    transform = EventCount(SENSOR, factor=2, threshold=0.3)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert rows(compiled) == event_count_reference(arr, SENSOR, 2, 0.3)


@pytest.mark.parametrize("threshold", [0.05, 1.0])
def test_sessions_in_odd_chunks_and_moving_between_paths(threshold, rng):
    arr = random_stream(rng, 1500, SENSOR, t_max=200)
    transform = EventCount(SENSOR, factor=(3, 2), threshold=threshold)
    whole, _ = both_paths(lambda: transform(arr))
    assert_sessions_on_both_paths(transform, arr, whole)


def test_one_step_gives_the_same_state_object_on_both_paths(rng):
    settings = EventCount(SENSOR, factor=(4, 3), threshold=0.3).settings
    first = Events.from_columns(*(torch.as_tensor(c) for c in (
        [1, 9, 2, 2], [0, 6, 1, 1], [5, 6, 7, 7], [True, False, True, True])))
    state = event_count_init(settings, first)
    state = EventCountState(state.level_sum + 3, state.reference + 1)  # a resumed stream
    before = [column.clone() for column in state[:2]]
    compiled, eager = both_paths(lambda: event_count_step(first, state, settings))
    assert_identical(compiled[0], eager[0])
    assert isinstance(compiled[1], EventCountState) and isinstance(eager[1], EventCountState)
    assert_identical(tuple(compiled[1]), tuple(eager[1]))
    assert_identical(list(state[:2]), before)  # the given state is not written


def test_batches_sorted_stacked_and_with_empty_recordings(rng):
    transform = EventCount(SENSOR, factor=(3, 2), threshold=0.2)

    def check(recording, out):
        assert rows(out) == event_count_reference(recording, SENSOR, (3, 2), 0.2)

    assert_batches_on_both_paths(transform, rng, SENSOR, 100, check)


def test_many_crossings_per_event_grow_the_output(rng):
    # Threshold 0.01 at factor 1: each event crosses 100 levels, far past the first buffer.
    arr = random_stream(rng, 3000, SENSOR, t_max=1000)
    transform = EventCount(SENSOR, factor=1, threshold=0.01)
    compiled, eager = both_paths(lambda: transform(arr))
    assert len(compiled) >= 100 * 3000
    assert_identical(compiled, eager)


@pytest.mark.parametrize("limit", [1, 299, 5_000])
def test_the_output_limit_raises_the_same_error_and_keeps_the_session(limit, rng):
    arr = random_stream(rng, 300, (8, 8, 2), t_max=50)
    transform = EventCount((8, 8, 2), factor=1, threshold=0.05)  # 20 crossings per event
    message = assert_output_limit_on_both_paths(transform, arr, limit, 20 * 290)
    assert "at least 5,800 events, more than the limit" in message


def test_an_event_outside_the_sensor_is_an_error_not_a_crash():
    events = Events.from_columns([0, 12], [0, 1], [1, 2], [True, True])
    with pytest.raises(ValueError, match=r"event 1 at \(x=12, y=1\) lies outside the sensor"):
        event_count(events, sensor_size=SENSOR, factor=(3, 2), threshold=0.5)


def test_a_huge_threshold_crosses_level_zero_only(rng):
    arr = random_stream(rng, 500, SENSOR, t_max=50)
    arr["p"][:] = np.arange(500) % 3 != 0  # the sums drift up and cross 0 on the way back
    for threshold in (1e300, 1e6):
        transform = EventCount(SENSOR, factor=1, threshold=threshold)
        compiled, eager = both_paths(lambda transform=transform: transform(arr))
        assert_identical(compiled, eager)
        assert rows(compiled) == event_count_reference(arr, SENSOR, 1, threshold)


def test_structured_output_keeps_the_input_dtype():
    arr = np.array([(0, 0, True, 5), (1, 1, True, 6)], dtype=DVS_DTYPE)
    compiled, eager = both_paths(lambda: EventCount((2, 2, 2), 2, threshold=0.5)(arr))
    assert compiled.dtype == DVS_DTYPE
    assert_identical(compiled, eager)
