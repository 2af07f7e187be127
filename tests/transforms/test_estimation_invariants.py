"""LinearEstimation and CubicEstimation: invariants, chunking, batches, devices and bad input.

The oracle comparisons and hand-computed cases are in ``test_estimation.py``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import evdown_torch.transforms.functional.estimation.cubic as cubic_module
import evdown_torch.transforms.functional.estimation.driver as estimation_module
import evdown_torch.transforms.functional.estimation.linear as linear_module
from evdown_torch import CubicEstimation, Events, LinearEstimation
from tests.helpers import (
    DVS_DTYPE,
    ESTIMATORS,
    FLOAT_DTYPE,
    LOG_LUMINANCE,
    as_tuples,
    assert_shift_equivariant,
    random_stream,
    unique_pixel_times,
)

SENSOR = (10, 7, 2)


@pytest.mark.parametrize("cls", LOG_LUMINANCE)
@pytest.mark.parametrize("dtype", [DVS_DTYPE, FLOAT_DTYPE])
def test_factor_one_threshold_one_returns_input(cls, dtype, rng):
    arr = unique_pixel_times(random_stream(rng, 3000, SENSOR, t_max=2000)).astype(dtype)
    if dtype is FLOAT_DTYPE:
        arr["t"] = arr["t"] * 1e-3 + 0.123456789  # times that floats do not hold exactly
    out = cls(SENSOR, factor=1, threshold=1.0)(arr)
    assert out.dtype == arr.dtype
    assert as_tuples(out) == as_tuples(arr)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    events=st.lists(
        st.tuples(st.integers(0, 2), st.integers(0, 1), st.integers(0, 30), st.booleans()),
        min_size=1,
        max_size=40,
        unique_by=lambda e: (e[0], e[1], e[2]),
    )
)
def test_factor_one_returns_input_for_any_stream(events):
    arr = np.array([(x, y, p, t) for x, y, t, p in events], dtype=DVS_DTYPE)
    for cls in ESTIMATORS:
        assert as_tuples(cls((3, 2, 2), factor=1)(arr)) == as_tuples(arr)


@pytest.mark.parametrize("cls", LOG_LUMINANCE)
@pytest.mark.parametrize("factor", [1, 3, (2, 5), (10, 7)])
def test_invariants(cls, factor, rng):
    arr = random_stream(rng, 1500, SENSOR, t_max=5000, sort=False)
    before = arr.copy()
    transform = cls(SENSOR, factor=factor, threshold=0.3)
    out = transform(arr)
    np.testing.assert_array_equal(arr, before)  # input untouched
    w, h, _ = transform.output_sensor_size
    assert out.dtype == arr.dtype and len(out) > 0
    assert np.all(np.diff(out["t"]) >= 0)
    assert out["x"].min() >= 0 and out["x"].max() < w
    assert out["y"].min() >= 0 and out["y"].max() < h
    assert out["t"].min() >= arr["t"].min() and out["t"].max() <= arr["t"].max()
    # Flipping every polarity flips every output polarity.
    flipped = arr.copy()
    flipped["p"] = ~flipped["p"]
    out_flipped = transform(flipped)
    np.testing.assert_array_equal(out_flipped[["x", "y", "t"]], out[["x", "y", "t"]])
    np.testing.assert_array_equal(out_flipped["p"], ~out["p"])
    # Shifting the clock (Unix-epoch microseconds, then 10**12 more) shifts every output.
    assert_shift_equivariant(transform, arr, out,
                             (1_700_000_000_000_000, 1_700_000_000_000_000 + 10**12))


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_factor_equal_to_sensor_gives_one_pixel(cls, rng):
    arr = random_stream(rng, 600, SENSOR, t_max=2000)
    transform = cls(SENSOR, factor=(10, 7), threshold=0.05)
    assert transform.output_sensor_size == (1, 1, 2)
    out = transform(arr)
    assert len(out) > 0 and set(out["x"].tolist()) == {0} and set(out["y"].tolist()) == {0}


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_chunking_does_not_change_the_result(cls, rng, monkeypatch):
    arr = random_stream(rng, 3000, (20, 12, 2), t_max=4000)
    transform = cls((20, 12, 2), factor=(3, 2), threshold=0.2)
    whole = transform(arr)
    monkeypatch.setattr(estimation_module, "REGION_CHUNK_EVENTS", 97)  # events per chunk
    monkeypatch.setattr(cubic_module, "CHUNK", 64)  # pixel-segment evaluations per chunk
    np.testing.assert_array_equal(transform(arr), whole)


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("max_delay", [None, 150])
def test_region_chunk_size_does_not_change_the_result(cls, max_delay, rng, monkeypatch):
    # estimate_window solves the regions in chunks of REGION_CHUNK_EVENTS events; chunks of a
    # few dozen events (many chunks, some of one region) give the same events, bit for bit,
    # for one stream and for a batch of recordings.
    arr = random_stream(rng, 3000, (20, 12, 2), t_max=4000)
    recordings = [random_stream(rng, 400, (20, 12, 2), t_max=3000) for _ in range(3)]
    transform = cls((20, 12, 2), factor=(3, 2), threshold=0.2, max_delay=max_delay)
    whole, batch = transform(arr), transform.batch(recordings)
    for size in (37, 500):
        monkeypatch.setattr(estimation_module, "REGION_CHUNK_EVENTS", size)
        monkeypatch.setattr(cubic_module, "CHUNK", 64)
        np.testing.assert_array_equal(transform(arr), whole)
        for got, expected in zip(transform.batch(recordings), batch, strict=True):
            np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("seed", range(6))
def test_float_batch_equals_each_recording_bit_for_bit(cls, seed, monkeypatch):
    # Recordings whose time scales differ by up to 1e9 (the steepest slope of a batch once set
    # the linear kernel's fixed point for all, and sums ran on across regions): each one's
    # output in a batch, or in a chunk with other regions, is its own output to the last bit.
    rng = np.random.default_rng(seed)
    recordings = []
    for _ in range(4):
        arr = random_stream(rng, 200, SENSOR, t_max=3000).astype(FLOAT_DTYPE)
        arr["t"] = arr["t"] * 10.0 ** rng.uniform(-9, 0) + rng.uniform(0, 100)
        recordings.append(arr)
    transform = cls(SENSOR, factor=2, threshold=0.3)
    alone = [transform(arr) for arr in recordings]
    for got, expected in zip(transform.batch(recordings), alone, strict=True):
        np.testing.assert_array_equal(got, expected)
    stream = np.concatenate([recordings[0], recordings[1]])
    stream["x"][len(recordings[0]):] = stream["x"][len(recordings[0]):] // 2  # other regions
    stream["x"][: len(recordings[0])] = stream["x"][: len(recordings[0])] // 2 + 5
    monkeypatch.setattr(estimation_module, "REGION_CHUNK_EVENTS", 150)
    chunked = transform(stream)
    monkeypatch.setattr(estimation_module, "REGION_CHUNK_EVENTS", 10**9)
    np.testing.assert_array_equal(transform(stream), chunked)


def test_local_cumsum_sums_each_segment_as_if_alone(rng):
    values = torch.from_numpy(rng.normal(size=5000) * 10.0 ** rng.uniform(-12, 12, 5000))
    first_at = torch.from_numpy(np.unique(np.concatenate([[0], rng.integers(1, 5000, 300)])))
    bounds = [*first_at.tolist(), 5000]
    expected = torch.cat([torch.cumsum(values[a:b], 0) for a, b in zip(bounds[:-1], bounds[1:])])
    assert torch.equal(linear_module.local_cumsum(values, first_at), expected)


@pytest.mark.parametrize("cls", LOG_LUMINANCE)
def test_empty_stream_gives_same_kind(cls):
    transform = cls(SENSOR, factor=2)
    out = transform(np.empty(0, dtype=DVS_DTYPE))
    assert out.dtype == DVS_DTYPE and out.shape == (0,)
    tensor_out = transform(torch.empty(0, 4, dtype=torch.float64))
    assert tensor_out.shape == (0, 4) and tensor_out.dtype == torch.float64
    ev_out = transform(Events.empty())
    assert isinstance(ev_out, Events) and ev_out.num_events == 0


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_tensor_input_on_device(cls, device, dtype):
    data = torch.tensor([[0, 0, 0, 1], [1, 0, 10, 1], [0, 0, 30, -1]], device=device,
                        dtype=dtype)
    out = cls((2, 1, 2), factor=(2, 1), threshold=0.25)(data)
    assert out.device == data.device and out.dtype == dtype
    # As test_linear_hand_computed (the crossing at 7.5); for the cubic, pixel 1's slopes are
    # 2 / 15, 0, 0 and the sum on [0, 10] is 1 + s + s^2 / 3 - 2 s^3 / 3, which is 1.5 at
    # s = 1 / 2 exactly. Integer times are rounded half up.
    crossing = {LinearEstimation: 7.5, CubicEstimation: 5.0}[cls]
    if dtype.is_floating_point:
        assert out[2, 2].item() == pytest.approx(crossing, rel=1e-12)
        out[2, 2] = crossing
    else:
        crossing = math.floor(crossing + 0.5)
    assert out.tolist() == [[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, crossing, 1], [0, 0, 30, -1]]


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize(
    ("threshold", "error"),
    [(0, ValueError), (-1.0, ValueError), (float("nan"), ValueError), (float("inf"), ValueError),
     (1e-9, ValueError), ("1", TypeError), (True, TypeError), (None, TypeError)],
)
def test_bad_threshold(cls, threshold, error):
    with pytest.raises(error, match="threshold"):
        cls(SENSOR, factor=2, threshold=threshold)


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_transform_is_frozen(cls):
    transform = cls(SENSOR, factor=2, threshold=0.5)
    with pytest.raises(AttributeError):
        transform.threshold = 1.0
    assert transform == cls(SENSOR, factor=2, threshold=0.5)


@pytest.mark.parametrize("cls", LOG_LUMINANCE)
def test_tonic_compose_to_frame(cls, nmnist):
    tonic = pytest.importorskip("tonic")
    sensor = tonic.datasets.NMNIST.sensor_size
    down = cls(sensor, factor=4, threshold=0.25)
    window = float(nmnist["t"].max() - nmnist["t"].min() + 1)
    to_frame = tonic.transforms.ToFrame(sensor_size=down.output_sensor_size, time_window=window)
    frames = tonic.transforms.Compose([down, to_frame])(nmnist)
    out = down(nmnist)
    assert out.dtype == nmnist.dtype and 0 < len(out) < len(nmnist)
    assert frames.shape == (1, 2, 9, 9)
    expected = np.zeros((2, 9, 9), dtype=np.int64)
    np.add.at(expected, (out["p"].astype(np.int64), out["y"], out["x"]), 1)
    np.testing.assert_array_equal(frames[0], expected)
