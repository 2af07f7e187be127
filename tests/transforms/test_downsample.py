"""Downsample and EventFunnelling against hand-computed cases, a slow reference and invariants."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch import Downsample, EventFunnelling, Events
from tests.helpers import DVS_DTYPE, as_tuples, funnel_reference, random_stream

SENSOR = (10, 7, 2)

# Every test on both CPU paths: the compiled loops and the eager kernels.
pytestmark = pytest.mark.usefixtures("kernels")


def test_downsample_hand_computed():
    ev = np.array([(9, 6, True, 30), (4, 3, False, 10), (5, 0, True, 20)], dtype=DVS_DTYPE)
    out = Downsample(SENSOR, factor=(3, 2))(ev)
    assert out.tolist() == [(1, 1, False, 10), (1, 0, True, 20), (3, 3, True, 30)]
    assert Downsample(SENSOR, factor=(3, 2)).output_sensor_size == (4, 4, 2)


def test_funnelling_hand_computed():
    ev = np.array(
        [(0, 0, True, 5), (1, 1, True, 5), (1, 1, False, 5), (2, 0, True, 5), (0, 1, True, 6)],
        dtype=DVS_DTYPE,
    )
    out = EventFunnelling(SENSOR, factor=2)(ev)
    assert out.tolist() == [(0, 0, True, 5), (0, 0, False, 5), (1, 0, True, 5), (0, 0, True, 6)]


@pytest.mark.parametrize("factor", [1, 2, 3, (2, 5), (10, 7), (4, 1)])
def test_funnelling_matches_slow_reference(factor, rng):
    arr = random_stream(rng, 2000, SENSOR, t_max=300, sort=False)
    fx, fy = (factor, factor) if isinstance(factor, int) else factor
    out = EventFunnelling(SENSOR, factor=factor)(arr)
    got = list(zip(out["x"].tolist(), out["y"].tolist(), out["t"].tolist(), out["p"].tolist()))
    assert got == funnel_reference(arr, fx, fy)


@pytest.mark.parametrize("cls", [Downsample, EventFunnelling])
@pytest.mark.parametrize("factor", [1, 3, (2, 5), (10, 7)])
def test_invariants(cls, factor, rng):
    arr = random_stream(rng, 500, SENSOR, sort=False)
    before = arr.copy()
    transform = cls(SENSOR, factor=factor)
    out = transform(arr)
    np.testing.assert_array_equal(arr, before)  # input untouched
    w, h, _ = transform.output_sensor_size
    assert out.dtype == arr.dtype
    assert np.all(np.diff(out["t"]) >= 0)
    assert out["x"].min() >= 0 and out["x"].max() < w and out["y"].max() < h
    shifted = arr.copy()
    shifted["t"] += 10**12 + 1_700_000_000_000_000
    out_shifted = transform(shifted)
    np.testing.assert_array_equal(out_shifted["t"] - out["t"], 10**12 + 1_700_000_000_000_000)
    np.testing.assert_array_equal(out_shifted[["x", "y", "p"]], out[["x", "y", "p"]])


def test_downsample_keeps_every_event_and_ties_keep_input_order():
    ev = np.array([(9, 0, True, 1), (0, 0, False, 1), (5, 6, True, 0)], dtype=DVS_DTYPE)
    out = Downsample(SENSOR, factor=5)(ev)
    assert out.tolist() == [(1, 1, True, 0), (1, 0, True, 1), (0, 0, False, 1)]


def test_factor_one_returns_input_multiset(rng):
    arr = random_stream(rng, 300, SENSOR)
    assert as_tuples(Downsample(SENSOR, factor=1)(arr)) == as_tuples(arr)


@pytest.mark.parametrize("cls", [Downsample, EventFunnelling])
def test_empty_stream_gives_same_kind(cls):
    transform = cls(SENSOR, factor=2)
    empty = np.empty(0, dtype=DVS_DTYPE)
    out = transform(empty)
    assert out.dtype == DVS_DTYPE and out.shape == (0,)
    tensor_out = transform(torch.empty(0, 4, dtype=torch.int64))
    assert tensor_out.shape == (0, 4) and tensor_out.dtype == torch.int64
    ev_out = transform(Events.empty())
    assert isinstance(ev_out, Events) and ev_out.num_events == 0


@pytest.mark.parametrize("cls", [Downsample, EventFunnelling])
def test_tensor_input_on_device(cls, device, dtype):
    data = torch.tensor([[9, 6, 30, 1], [4, 3, 10, -1], [4, 2, 10, -1]], device=device,
                        dtype=dtype)
    out = cls(SENSOR, factor=5)(data)
    assert out.device == data.device and out.dtype == dtype
    expected = [[0, 0, 10, -1], [0, 0, 10, -1], [1, 1, 30, 1]]
    if cls is EventFunnelling:
        expected = [[0, 0, 10, -1], [1, 1, 30, 1]]
    assert out.tolist() == expected


def test_float_tensor_input_stays_float():
    data = torch.tensor([[9.0, 6.0, 0.5, 1.0], [4.0, 3.0, 0.25, 0.0]], dtype=torch.float64)
    out = Downsample(SENSOR, factor=2)(data)
    assert out.dtype == torch.float64
    assert out.tolist() == [[2.0, 1.0, 0.25, 0.0], [4.0, 3.0, 0.5, 1.0]]


@pytest.mark.parametrize(
    ("factor", "error", "match"),
    [
        (0, ValueError, "positive integer"),
        (-2, ValueError, "positive integer"),
        (1.5, ValueError, "positive integer"),
        ((2, 0), ValueError, "positive integer"),
        ((2, 2, 2), TypeError, "pair"),
        ("2", TypeError, "pair"),
        (True, TypeError, "pair"),
        (11, ValueError, "larger than the sensor"),
        ((1, 8), ValueError, "larger than the sensor"),
    ],
)
def test_bad_factor(factor, error, match):
    with pytest.raises(error, match=match):
        Downsample(SENSOR, factor=factor)


@pytest.mark.parametrize(
    ("sensor_size", "error"),
    [((10, 7), TypeError), ((10, 7, 2, 1), TypeError), ((0, 7, 2), ValueError),
     ((10, 7, 3), ValueError), ((10.0, 7, 2), TypeError), (None, TypeError)],
)
def test_bad_sensor_size(sensor_size, error):
    with pytest.raises(error, match="sensor_size"):
        EventFunnelling(sensor_size, factor=1)


def test_transform_is_frozen_and_not_mutated(rng):
    transform = Downsample(SENSOR, factor=2)
    transform(random_stream(rng, 10, SENSOR))
    with pytest.raises(AttributeError):
        transform.factor = 3
    assert transform == Downsample(SENSOR, factor=2)


def test_tonic_compose_to_frame_round_trip(nmnist):
    tonic = pytest.importorskip("tonic")
    sensor = tonic.datasets.NMNIST.sensor_size
    for cls in (Downsample, EventFunnelling):
        down = cls(sensor, factor=4)
        # One time window spanning the recording: Tonic bins every event into one frame.
        window = float(nmnist["t"].max() - nmnist["t"].min() + 1)
        to_frame = tonic.transforms.ToFrame(sensor_size=down.output_sensor_size, time_window=window)
        frames = tonic.transforms.Compose([down, to_frame])(nmnist)
        assert frames.shape == (1, 2, 9, 9)
        out = down(nmnist)
        assert out.dtype == nmnist.dtype and out.dtype.names == nmnist.dtype.names
        # Frame channel 1 is ON, channel 0 OFF; each cell counts the events of one region.
        expected = np.zeros((2, 9, 9), dtype=np.int64)
        np.add.at(expected, (out["p"].astype(np.int64), out["y"], out["x"]), 1)
        np.testing.assert_array_equal(frames[0], expected)
        assert int(frames.sum()) == len(out)
    assert len(Downsample(sensor, factor=4)(nmnist)) == len(nmnist)
    assert len(EventFunnelling(sensor, factor=4)(nmnist)) < len(nmnist)


def test_funnelling_in_chunks_never_splits_a_timestamp(rng, monkeypatch):
    import evdown_torch._tensors as common

    arr = random_stream(rng, 3000, SENSOR, t_max=40)  # about 75 events per timestamp
    whole = EventFunnelling(SENSOR, factor=2)(arr)
    monkeypatch.setattr(common, "CHUNK_EVENTS", 10)
    np.testing.assert_array_equal(EventFunnelling(SENSOR, factor=2)(arr), whole)
    got = list(zip(whole["x"].tolist(), whole["y"].tolist(), whole["t"].tolist(),
                   whole["p"].tolist()))
    assert got == funnel_reference(arr, 2, 2)


WIDE_DTYPE = np.dtype([("x", "<i4"), ("y", "<i4"), ("p", "?"), ("t", "<i8")])


@pytest.mark.parametrize(
    ("sensor", "factor"),
    [((200, 100, 2), 1),  # 40,000 keys: sorted as int32
     ((70_000, 40_000, 2), 1),  # 5.6e9 keys: sorted as int64
     ((70_000, 40_000, 2), (1000, 3))],
)
def test_funnelling_on_large_output_sensors_matches_the_reference(sensor, factor, rng):
    # A few pixels far apart, repeated at few timestamps: many repeats on a wide key range.
    pixels = np.stack([rng.integers(0, sensor[0], 12), rng.integers(0, sensor[1], 12)], 1)
    pick = rng.integers(0, 12, 3000)
    arr = np.empty(3000, dtype=WIDE_DTYPE)
    arr["x"], arr["y"] = pixels[pick, 0], pixels[pick, 1]
    arr["t"] = rng.integers(0, 30, 3000)
    arr["p"] = rng.random(3000) < 0.5
    fx, fy = (factor, factor) if isinstance(factor, int) else factor
    transform = EventFunnelling(sensor, factor=factor)
    out = transform(arr)
    got = list(zip(out["x"].tolist(), out["y"].tolist(), out["t"].tolist(), out["p"].tolist()))
    assert got == funnel_reference(arr, fx, fy)
    in_order = arr[np.argsort(arr["t"], kind="stable")]
    session = transform.session()
    parts = [session(chunk) for chunk in np.array_split(in_order, 7)]
    np.testing.assert_array_equal(np.concatenate(parts), out)


def test_drop_repeats_compares_with_seen_events_beyond_the_chunks_coordinates():
    from evdown_torch.transforms.functional.funnelling import drop_repeats

    # seen (5, 0, ON) and the chunk's (2, 1, ON) would share a key built on the chunk's own
    # width (3): 2 * (0 * 3 + 5) + 1 == 2 * (1 * 3 + 2) + 1.
    seen = Events.from_columns([5], [0], [7], [1])
    ev = Events.from_columns([2, 2, 0], [1, 1, 0], [7, 7, 8], [1, 1, 1])
    out = drop_repeats(ev, seen=seen)
    assert list(zip(out.x.tolist(), out.y.tolist(), out.t.tolist())) == [(2, 1, 7), (0, 0, 8)]


def test_funnelling_output_never_shares_memory_with_the_input():
    from evdown_torch.transforms.functional.funnelling import drop_repeats, event_funnelling

    ev = Events.from_columns([0, 1, 2], [0, 0, 0], [1, 2, 3], [1, 0, 1])  # no repeats
    for out in (event_funnelling(ev, factor=(1, 1)), drop_repeats(ev)):
        for a, b in zip(out, ev):
            assert torch.equal(a, b)
            assert a.data_ptr() != b.data_ptr()


def test_to_regions_keeps_the_given_order_in_new_tensors():
    from evdown_torch.transforms.functional.downsample import to_regions

    ev = Events.from_columns([5, 0, 9], [6, 1, 0], [30, 10, 20], [1, 0, 1])  # not time-sorted
    out = to_regions(ev, (3, 2))
    assert list(zip(*(column.tolist() for column in out))) == [
        (1, 3, 30, True), (0, 0, 10, False), (3, 0, 20, True)]
    for a, b in zip(out, ev):
        assert a.data_ptr() != b.data_ptr()
