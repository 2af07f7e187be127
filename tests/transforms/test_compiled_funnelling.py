"""Downsample, EventFunnelling and TemporalFunnelling: compiled CPU loops against the eager
kernels and the slow references."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

from evdown_torch import (
    Chain,
    Downsample,
    EventFunnelling,
    Events,
    TemporalFunnelling,
    eager_kernels,
)
from evdown_torch.transforms.functional.funnelling import drop_repeats, funnelling_sorted
from evdown_torch.transforms.functional.temporal import bin_index, bin_start
from tests.helpers import (
    FLOAT_DTYPE,
    assert_identical,
    assert_sessions_on_both_paths,
    both_paths,
    funnel_reference,
    random_stream,
    rows,
    spy,
    temporal_reference,
)

pytest.importorskip("numba")

SENSOR = (10, 7, 2)
FACTORS = [1, 2, 3, (2, 5), (3, 1), (4, 3), (10, 7)]
FUNNELLING = importlib.import_module("evdown_torch.transforms.functional.compiled.funnelling")
TEMPORAL = importlib.import_module("evdown_torch.transforms.functional.compiled.temporal")


def _pair(factor):
    return (factor, factor) if isinstance(factor, int) else factor


@pytest.mark.parametrize("factor", FACTORS)
def test_downsample_and_funnelling_equal_eager_and_the_reference(factor, rng):
    arr = random_stream(rng, 2000, SENSOR, t_max=150, sort=False)  # many repeats
    fx, fy = _pair(factor)
    for cls in (Downsample, EventFunnelling):
        transform = cls(SENSOR, factor=factor)
        compiled, eager = both_paths(lambda transform=transform: transform(arr))
        assert_identical(compiled, eager)
    order = np.argsort(arr["t"], kind="stable")
    assert rows(both_paths(lambda: Downsample(SENSOR, factor=factor)(arr))[0]) == [
        (int(arr["x"][i]) // fx, int(arr["y"][i]) // fy, int(arr["t"][i]), bool(arr["p"][i]))
        for i in order]
    assert rows(compiled) == funnel_reference(arr, fx, fy)


@pytest.mark.parametrize("sensor", [None, (8, 6, 2), (9, 11, 2)])  # the grid found or given
@pytest.mark.parametrize("dt", [1, 7, 250, 10**9])
def test_temporal_funnelling_equals_eager_and_the_reference(dt, sensor, rng):
    arr = random_stream(rng, 1500, (8, 6, 2), t_max=2000, sort=False)
    transform = TemporalFunnelling(dt=dt, sensor_size=sensor)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert rows(compiled) == temporal_reference(arr, dt)


@pytest.mark.parametrize("dtype", [np.int64, np.float32, np.float64])
def test_timestamp_dtypes_near_their_limits(dtype, rng):
    arr = random_stream(rng, 900, SENSOR, t_max=40, sort=False)
    if dtype == np.int64:
        t = arr["t"] + (2**63 - 50)
    else:
        t = arr["t"].astype(dtype) * dtype(0.5) + dtype(3e5)
    data = torch.tensor(np.stack([arr["x"], arr["y"], t, arr["p"]], 1).astype(dtype))
    for transform in (Downsample(SENSOR, factor=(3, 2)), EventFunnelling(SENSOR, factor=(3, 2)),
                      TemporalFunnelling(dt=4 if dtype == np.int64 else 2.5)):
        compiled, eager = both_paths(lambda transform=transform: transform(data))
        assert_identical(compiled, eager)
        assert compiled.dtype == data.dtype and len(compiled) > 0


def test_float64_seconds(rng):
    arr = random_stream(rng, 700, SENSOR, t_max=100, dtype=FLOAT_DTYPE, sort=False)
    arr["t"] = arr["t"] * 1e-3 + 1.7e9
    for transform in (EventFunnelling(SENSOR, factor=2), TemporalFunnelling(dt=0.004)):
        compiled, eager = both_paths(lambda transform=transform: transform(arr))
        assert_identical(compiled, eager)
    assert rows(compiled) == temporal_reference(arr, 0.004)


@pytest.mark.parametrize("name", ["downsample", "funnelling", "temporal", "temporal_on_its_sensor",
                                  "temporal_then_funnel"])
def test_sessions_in_odd_chunks_and_moving_between_paths(name, rng):
    transform = {
        "downsample": Downsample(SENSOR, factor=(3, 2)),
        "funnelling": EventFunnelling(SENSOR, factor=(3, 2)),
        "temporal": TemporalFunnelling(dt=5),
        "temporal_on_its_sensor": TemporalFunnelling(dt=5, sensor_size=SENSOR),
        "temporal_then_funnel": Chain(TemporalFunnelling(dt=3),
                                      EventFunnelling(SENSOR, factor=2)),
    }[name]
    arr = random_stream(rng, 1500, SENSOR, t_max=120)  # runs of equal t cut by the chunks
    whole, _ = both_paths(lambda: transform(arr))
    assert_sessions_on_both_paths(transform, arr, whole)


@pytest.mark.parametrize("factor", [(1, 1), (2, 4), (4, 1), (8, 8), (3, 2), (4, 3)])
def test_downsample_floors_coordinates_beyond_the_sensor(factor):
    # A stacked batch's rows lie far past one sensor: shifts and tables both floor them.
    from evdown_torch.transforms.functional.compiled.downsample import downsample_step
    from evdown_torch.transforms.functional.settings import RegionSettings

    x = [0, 9, 10, 4095, 4096, 70_001, -1, -9, 2**40 + 3]
    y = [6, 7, 8191, 8192, 123_457, 5, -2, -8, 2**50 + 1]
    events = Events.from_columns(x, y, list(range(len(x))), [True] * len(x))
    out = downsample_step(events, RegionSettings((16, 16, 2), factor))
    fx, fy = factor
    assert out.x.tolist() == [v // fx for v in x]
    assert out.y.tolist() == [v // fy for v in y]
    assert out.t.tolist() == events.t.tolist() and out.p.tolist() == events.p.tolist()


@pytest.mark.parametrize("cls", [Downsample, EventFunnelling])
def test_batches_sorted_stacked_and_with_empty_recordings(cls, rng):
    transform = cls(SENSOR, factor=(3, 2))
    recordings = [random_stream(rng, n, SENSOR, t_max=30) for n in (50, 0, 300, 1, 120)]
    unsorted = [random_stream(rng, n, SENSOR, t_max=30, sort=False) for n in (80, 0, 200)]
    for batch in (recordings, unsorted):
        compiled, eager = both_paths(lambda batch=batch: transform.batch(batch))
        assert_identical(compiled, eager)
        if cls is EventFunnelling:
            for recording, out in zip(batch, compiled, strict=True):
                assert rows(out) == funnel_reference(recording, 3, 2)


def test_a_recording_boundary_starts_a_run_in_a_batch():
    # Two recordings holding the same event at the same t: each keeps its own.
    same = np.array([(1, 1, True, 5), (0, 0, True, 5)], dtype=random_stream(
        np.random.default_rng(0), 1, SENSOR).dtype)
    compiled, eager = both_paths(lambda: EventFunnelling(SENSOR, factor=2).batch([same, same]))
    assert_identical(compiled, eager)
    assert [len(out) for out in compiled] == [1, 1]


def test_seen_events_drop_repeats_in_the_first_run_only():
    seen = Events.from_columns([1, 4], [0, 2], [5, 5], [True, False])
    chunk = Events.from_columns([1, 1, 4, 4, 1], [0, 0, 2, 2, 0], [5, 5, 5, 6, 6],
                                [True, False, False, False, True])
    compiled, eager = both_paths(lambda: drop_repeats(chunk, seen=seen))
    assert_identical(compiled, eager)
    assert list(zip(*(column.tolist() for column in compiled))) == [
        (1, 0, 5, False), (4, 2, 6, False), (1, 0, 6, True)]
    later = Events.from_columns([1], [0], [7], [True])  # after seen's time: nothing dropped
    compiled, eager = both_paths(lambda: drop_repeats(later, seen=seen))
    assert_identical(compiled, eager)
    assert compiled.num_events == 1


def test_a_grid_too_large_for_the_table_goes_to_the_eager_kernel(monkeypatch, rng):
    taken = spy(monkeypatch, FUNNELLING, "_funnel")
    wide = np.dtype([("x", "<i4"), ("y", "<i4"), ("p", "?"), ("t", "<i8")])
    arr = random_stream(rng, 300, (70_000, 40_000, 2), t_max=20, dtype=wide)
    arr[150:] = arr[:150]  # repeats
    arr.sort(order="t", kind="stable")
    compiled, eager = both_paths(lambda: EventFunnelling((70_000, 40_000, 2), factor=1)(arr))
    assert_identical(compiled, eager)
    assert taken == [] and len(compiled) < 300
    small = EventFunnelling(SENSOR, factor=1)(random_stream(rng, 300, SENSOR, t_max=20))
    assert len(small) > 0 and len(taken) == 1


def test_an_event_outside_the_given_grid_is_an_error_not_a_crash():
    events = Events.from_columns([0, 9], [0, 1], [1, 2], [True, True])
    with pytest.raises(ValueError, match=r"event 1 at \(x=9, y=1\) lies outside the sensor"):
        funnelling_sorted(events, (2, 2), size=(3, 3))


@pytest.mark.parametrize("dt", [1, 3, 1000, 2**62, 2**63 - 1])
@pytest.mark.parametrize("origin", [-(2**63), -7, 0, 2**62])
def test_bin_starts_equal_eager_and_python_integers(dt, origin, monkeypatch, rng):
    # Unsorted times (a division at every change of bin) and sorted ones, up to int64's limit.
    offsets = [0, 1, 2, 999, 1000, 1001, 5, 2**62, 3, 2**63 - 1 - max(origin, 0)]
    offsets += rng.integers(0, 5000, 200).tolist()
    offsets = [o for o in offsets if origin + o <= 2**63 - 1]
    for order in (offsets, sorted(offsets)):
        t = torch.tensor([origin + o for o in order], dtype=torch.int64)
        calls = spy(monkeypatch, TEMPORAL, "_bins_loop")
        compiled, eager = both_paths(lambda t=t: bin_start(t, dt=dt, t_start=origin))
        assert len(calls) == 1  # the compiled loop ran (once: the eager path has none)
        assert_identical(compiled, eager)
        assert compiled.tolist() == [origin + (o // dt) * dt for o in order]
        compiled, eager = both_paths(lambda t=t: bin_index(t, dt=dt, t_start=origin))
        assert len(calls) == 2
        assert_identical(compiled, eager)
        assert compiled.tolist() == [o // dt for o in order]


def test_bin_starts_refuse_offsets_past_int64_on_both_paths():
    t = torch.tensor([-5, 2**63 - 1], dtype=torch.int64)  # 2**63 + 4 from the origin
    for forced in (False, True):
        for bins in (bin_start, bin_index):
            with eager_kernels(forced), pytest.raises(ValueError, match="span 2\\*\\*63 or more"):
                bins(t, dt=10, t_start=-5)


def test_bin_starts_of_other_integer_dtypes_keep_their_dtype_on_both_paths():
    t = torch.tensor([3, 9, 10, 25, 4], dtype=torch.int32)
    compiled, eager = both_paths(lambda: bin_start(t, dt=10, t_start=3))
    assert_identical(compiled, eager)
    assert compiled.dtype == torch.int32 and compiled.tolist() == [3, 3, 3, 23, 3]
