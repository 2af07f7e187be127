"""The estimators' compiled window against the eager driver and the slow references."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

from evdown_torch import (
    CubicEstimation,
    Events,
    LinearEstimation,
    eager_kernels,
    max_output_events,
)
from evdown_torch.transforms.functional.compiled import cubic as compiled_cubic
from evdown_torch.transforms.functional.compiled import estimation as compiled_estimation
from evdown_torch.transforms.functional.estimation import driver
from evdown_torch.transforms.functional.estimation.method import (
    cubic_estimation,
    linear_estimation,
)
from tests.helpers import (
    ESTIMATORS,
    FLOAT_DTYPE,
    assert_batches_on_both_paths,
    assert_compiled_then_eager,
    assert_identical,
    assert_matches_reference,
    assert_sessions_on_both_paths,
    both_paths,
    exact_linear_reference,
    near_their_limits,
    random_stream,
    reference,
    spy,
    unique_pixel_times,
)

pytest.importorskip("numba")

SENSOR = (10, 7, 2)
FACTORS = [1, 2, 3, (2, 3), (3, 1), (4, 3), (10, 7)]  # (3, 1), (4, 3): not dividing
THRESHOLDS = [0.05, 0.123457, 0.3, 1.0, 2.5, 100.0]


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("factor", FACTORS)
@pytest.mark.parametrize("threshold", THRESHOLDS)
@pytest.mark.parametrize("max_delay", [None, 4])
def test_compiled_equals_eager(cls, factor, threshold, max_delay, rng):
    arr = random_stream(rng, 900, SENSOR, t_max=250, sort=False)
    transform = cls(SENSOR, factor=factor, threshold=threshold, max_delay=max_delay)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("max_delay", [None, 50])
def test_compiled_equals_eager_with_regions_and_pixels_sparse_next_to_the_events(cls, max_delay,
                                                                                 rng):
    # A wide sensor, a large factor and few events: the window's regions span far more ids
    # than it has events (grouped by the radix sort, not by counting) and every region has
    # far fewer events than pixels (its events put in pixel order by the merge sort). Each
    # region's events fall on a few of its pixels, mostly ON, so that levels are crossed.
    sensor, regions, per_region = (4096, 2048, 2), 30, 40
    n = regions * per_region
    region = np.repeat(rng.choice(256 * 128, regions, replace=False), per_region)
    arr = random_stream(rng, n, sensor, t_max=10_000, sort=False)
    arr["x"] = (region % 256) * 16 + rng.integers(0, 4, n)
    arr["y"] = (region // 256) * 16 + rng.integers(0, 4, n)
    arr["p"] = rng.random(n) < 0.9
    assert region.max() + 1 > 4 * n + 1024  # group_by_region's sparse case
    assert 4 * per_region + 64 < 16 * 16  # region_knots's few-events case
    transform = cls(sensor, factor=16, threshold=0.05, max_delay=max_delay)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert len(compiled) > 0


@pytest.mark.parametrize("factor", [(1, 1), (2, 2), (4, 3)])
def test_compiled_matches_the_exact_reference(factor, rng):
    arr = unique_pixel_times(random_stream(rng, 300, SENSOR, t_max=2000))
    with eager_kernels(False):
        out = LinearEstimation(SENSOR, factor=factor, threshold=0.3)(arr)
    assert_matches_reference(out, exact_linear_reference(arr, SENSOR, factor, 0.3), True)


@pytest.mark.parametrize("factor", [(1, 1), (2, 2), (4, 3)])
def test_compiled_cubic_matches_scipys_pchip(factor, rng):
    pytest.importorskip("scipy")
    arr = unique_pixel_times(random_stream(rng, 300, SENSOR, t_max=2000))
    with eager_kernels(False):
        out = CubicEstimation(SENSOR, factor=factor, threshold=0.3)(arr)
    assert_matches_reference(out, reference(arr, SENSOR, factor, 0.3, "cubic"), True)


def test_the_compiled_window_runs_and_the_eager_solver_does_not(monkeypatch, rng):
    compiled_module = importlib.import_module("evdown_torch.transforms.functional.compiled."
                                              "estimation")
    arr = random_stream(rng, 100, SENSOR)
    assert_compiled_then_eager(monkeypatch, (compiled_module, "_window_loop_of"),
                               (driver, "pixel_knots"),
                               lambda: LinearEstimation(SENSOR, factor=2, threshold=0.5)(arr))


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("dtype", [np.int64, np.float32, np.float64])
@pytest.mark.parametrize("max_delay", [None, 3])
def test_timestamp_dtypes_near_their_limits(cls, dtype, max_delay, rng):
    arr = random_stream(rng, 800, SENSOR, t_max=50, sort=False)
    data = near_their_limits(arr, dtype, 50)  # int64 up to 2**63 - 11
    transform = cls(SENSOR, factor=(3, 2), threshold=0.25, max_delay=max_delay)
    compiled, eager = both_paths(lambda: transform(data))
    assert_identical(compiled, eager)
    assert len(compiled) > 0


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_float64_timestamps_in_seconds(cls, rng):
    arr = random_stream(rng, 600, SENSOR, t_max=200, dtype=FLOAT_DTYPE, sort=False)
    arr["t"] = arr["t"] * 1e-6 + 1.7e9  # seconds since 1970: pieces of a few ulps
    for max_delay in (None, 3e-6):
        transform = cls(SENSOR, factor=2, threshold=0.3, max_delay=max_delay)
        compiled, eager = both_paths(lambda transform=transform: transform(arr))
        assert_identical(compiled, eager)


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("threshold", [0.05, 0.3, 2.5])
@pytest.mark.parametrize("max_delay", [1, 7, 10**6])
def test_sessions_in_odd_chunks_and_moving_between_paths(cls, threshold, max_delay, rng):
    arr = random_stream(rng, 1500, SENSOR, t_max=600)
    transform = cls(SENSOR, factor=(3, 2), threshold=threshold, max_delay=max_delay)
    whole, eager_whole = both_paths(lambda: transform(arr))
    assert_identical(whole, eager_whole)
    assert_sessions_on_both_paths(transform, arr, whole)


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("max_delay", [None, 5])
def test_batches_sorted_stacked_and_with_empty_recordings(cls, max_delay, rng):
    transform = cls(SENSOR, factor=(3, 2), threshold=0.2, max_delay=max_delay)

    def check(recording, out):  # each recording as if alone, on the eager path
        with eager_kernels():
            assert_identical(out, transform(recording))

    assert_batches_on_both_paths(transform, rng, SENSOR, 100, check)


def test_one_event_and_a_stream_at_one_time():
    one = Events.from_columns([3], [2], [7], [True])  # the region's mean +1/4: one ON
    cancelled = Events.from_columns([0, 1, 1, 0], [0, 0, 0, 1], [5, 5, 5, 5],
                                    [True, True, False, False])  # levels +1, 0, -1: mean 0
    for kernel in (linear_estimation, cubic_estimation):
        for events, times in ((one, [7]), (cancelled, [])):
            compiled, eager = both_paths(lambda events=events, kernel=kernel: kernel(
                events, sensor_size=SENSOR, factor=(2, 2), threshold=0.25))
            assert_identical(compiled, eager)
            assert compiled.t.tolist() == times


def test_hand_computed_ramps():
    # Two pixels of one region: the mean rises 0 -> 1/2 -> 1 over [0, 10] (levels 0.25 apart).
    events = Events.from_columns([0, 1], [0, 0], [0, 10], [1, 1])
    with eager_kernels(False):
        out = linear_estimation(events, sensor_size=(2, 1, 2), factor=(2, 1), threshold=0.25)
    assert out.t.tolist() == [0, 0, 5, 10] and out.p.tolist() == [True] * 4
    # Cubic: the docstring example of cubic_estimation, whose curve reaches the region's third
    # level at t = 6.18 (rounded to 6) where the polyline reaches it at 10.
    events = Events.from_columns([0, 1, 0], [0, 0, 0], [0, 10, 20], [1, 1, 0])
    with eager_kernels(False):
        out = cubic_estimation(events, sensor_size=(2, 1, 2), factor=(2, 1), threshold=0.25)
    assert out.t.tolist() == [0, 0, 6, 20] and out.p.tolist() == [True, True, True, False]


def test_the_cubic_loop_rounds_its_multiply_adds_as_torch_does(monkeypatch, rng):
    # Float timestamps keep every crossing's float time: rounding the pieces' multiply-adds
    # otherwise than torch's addcmul moves some of them.
    arr = random_stream(rng, 20000, (34, 34, 2), t_max=300000, dtype=FLOAT_DTYPE)
    arr["t"] = arr["t"] * 1.37e-3
    transform = CubicEstimation((34, 34, 2), factor=(3, 2), threshold=0.1)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    fused = compiled_cubic.addcmul_is_fused()
    assert fused is not None  # every CPU this runs on: one rounding or two, as torch does
    monkeypatch.setattr(compiled_estimation, "addcmul_is_fused", lambda: not fused)
    with eager_kernels(False):
        other = transform(arr)
    assert len(other) != len(eager) or (other["t"] != eager["t"]).any()


def test_the_cubic_derivative_roots_take_a_correctly_rounded_sqrt():
    # Found by a differential search: torch's CPU sqrt rounds sqrt(6.167086359879541), a
    # piece's discriminant here, one unit below the nearest float; the derivative root that
    # bounds the piece's Newton search moved by one unit, and with it the first crossing's
    # float time (7855.437806798385 eager against ...387 compiled).
    arr = np.array([(19, 31, 203.0, True), (11, 13, 9593.0, False), (8, 15, 10783.0, False),
                    (8, 15, 19467.0, True), (8, 12, 31391.0, True), (10, 14, 57428.0, False),
                    (11, 14, 99010.0, True), (10, 0, 99888.0, False)],
                   dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
    transform = CubicEstimation((22, 35, 2), factor=4, threshold=0.1)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert eager["t"].tolist()[:1] == [7855.437806798387]


def test_without_torchs_rounding_known_the_cubic_method_stays_eager(monkeypatch, rng):
    monkeypatch.setattr(compiled_cubic, "addcmul_is_fused", lambda: None)
    loops = spy(monkeypatch, compiled_estimation, "_window_loop_of")
    arr = random_stream(rng, 200, SENSOR, t_max=100)
    with eager_kernels(False):
        CubicEstimation(SENSOR, factor=2, threshold=0.3)(arr)
        assert not loops
        LinearEstimation(SENSOR, factor=2, threshold=0.3)(arr)
    assert len(loops) == 1


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("limit", [1, 37, 500])
def test_the_output_limit_raises_the_same_error_in_small_region_chunks(cls, limit, monkeypatch,
                                                                       rng):
    monkeypatch.setattr(driver, "REGION_CHUNK_EVENTS", 64)  # many chunks, as on a big window
    arr = random_stream(rng, 700, SENSOR, t_max=300)
    transform = cls(SENSOR, factor=1, threshold=0.05)
    messages = []
    for eager in (False, True):
        with eager_kernels(eager), max_output_events(limit), pytest.raises(ValueError) as error:
            transform(arr)
        messages.append(str(error.value))
    assert messages[0] == messages[1] and "more than the limit" in messages[0]
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)


def test_an_event_outside_the_sensor_is_an_error_not_a_crash():
    for x, kernel in ((12, linear_estimation), (-3, cubic_estimation)):
        events = Events.from_columns([0, x], [0, 1], [1, 2], [True, True])
        with eager_kernels(False), pytest.raises(ValueError, match=r"event 1 at \(x=.*lies "
                                                                      "outside the sensor"):
            kernel(events, sensor_size=SENSOR, factor=(3, 2), threshold=0.5)


@pytest.mark.parametrize("kernel", [linear_estimation, cubic_estimation])
def test_the_input_is_not_written(kernel, rng):
    arr = random_stream(rng, 400, SENSOR, t_max=100)
    events = Events.from_columns(*(torch.as_tensor(arr[c].astype(np.int64))
                                   for c in ("x", "y", "t")), torch.as_tensor(arr["p"]))
    before = [column.clone() for column in events]
    with eager_kernels(False):
        kernel(events, sensor_size=SENSOR, factor=2, threshold=0.1, max_delay=5)
    assert_identical(list(events), before)


@pytest.mark.parametrize("curve", ["linear", "cubic"])
def test_a_level_change_too_wide_to_pack_is_left_to_the_eager_driver(curve, monkeypatch):
    # A session's first knot of a pixel carries its whole level: 2**31 does not fit the 32
    # bits the loop packs a change in, so the window takes the eager driver (the same events).
    from evdown_torch.transforms.functional.estimation.settings import EstimationSettings

    settings = EstimationSettings((4, 4, 2), (2, 2), 2.0**27, max_delay=3, curve=curve)
    events = Events.from_columns([0, 1, 0], [0, 0, 1], [0, 4, 9], [True, False, True])
    change = torch.tensor([2**31, -5, 1])

    def window():
        return driver.estimate_window(events, change=change, t_start=events.t[0],
                                      t_end=events.t[-1], settings=settings)

    eager_solves = spy(monkeypatch, driver, "pixel_knots")
    compiled, eager = both_paths(window)
    assert_identical(compiled[0], eager[0])
    assert len(eager_solves) == 2  # both paths solved it eagerly
    # The region's mean jumps to 2**31 / 4 = 4 levels of 2**27 at t = 0; the rest moves it
    # by far less than a level.
    assert compiled[0].t.tolist() == [0, 0, 0, 0] and compiled[0].p.all()
