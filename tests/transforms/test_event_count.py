"""EventCount against a slow exact reference, hand-computed cases, invariants and streaming."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from evdown_torch import EventCount, Events
from tests.helpers import DVS_DTYPE, as_tuples, event_count_reference, random_stream, rows

SENSOR = (10, 7, 2)

# Every test on both CPU paths: the compiled loop and the eager kernel.
pytestmark = pytest.mark.usefixtures("kernels")


def test_hand_computed_region():
    # One 2x2 region, theta 0.5: a region threshold of 2 events. ON, ON -> ON at t=2;
    # ON, OFF, OFF -> the mean falls back to 0.25 (no event), then 0 -> OFF at t=5.
    ev = np.array(
        [(0, 0, True, 1), (1, 0, True, 2), (0, 1, True, 3), (1, 1, False, 4), (1, 1, False, 5),
         (0, 0, False, 5)],
        dtype=DVS_DTYPE,
    )
    out = EventCount((2, 2, 2), factor=2, threshold=0.5)(ev)
    assert out.tolist() == [(0, 0, True, 2), (0, 0, False, 5)]


def test_several_levels_at_one_instant_and_no_event_after_reversal():
    # theta 0.25 on a 1x2 region: each event moves the mean by 0.5, crossing two levels.
    ev = torch.tensor([[0, 0, 1, 1], [0, 1, 2, 1], [0, 1, 3, 0]])
    out = EventCount((1, 2, 2), factor=(1, 2), threshold=0.25)(ev)
    assert out.tolist() == [[0, 0, 1, 1], [0, 0, 1, 1], [0, 0, 2, 1], [0, 0, 2, 1],
                            [0, 0, 3, 0], [0, 0, 3, 0]]


@pytest.mark.parametrize("factor", [1, 2, 3, 4, (2, 3), (10, 7), (3, 1)])
@pytest.mark.parametrize("threshold", [0.01, 0.3, 1.0, 2.5, 100.0])
def test_matches_exact_reference(factor, threshold, rng):
    arr = random_stream(rng, 1500, SENSOR, t_max=400, sort=False)
    out = EventCount(SENSOR, factor=factor, threshold=threshold)(arr)
    assert rows(out) == event_count_reference(arr, SENSOR, factor, threshold)


def test_factor_one_threshold_one_returns_input(rng):
    arr = random_stream(rng, 800, SENSOR, t_max=100_000)
    assert as_tuples(EventCount(SENSOR, factor=1, threshold=1.0)(arr)) == as_tuples(arr)


@pytest.mark.parametrize("factor", [2, (3, 2)])
def test_invariants_flip_shift_sorted_inside(factor, rng):
    arr = random_stream(rng, 1000, SENSOR, t_max=1000, sort=False)
    before = arr.copy()
    transform = EventCount(SENSOR, factor=factor, threshold=0.25)
    out = transform(arr)
    np.testing.assert_array_equal(arr, before)
    w, h, _ = transform.output_sensor_size
    assert np.all(np.diff(out["t"]) >= 0)
    assert out["x"].max() < w and out["y"].max() < h and out["x"].min() >= 0
    flipped = arr.copy()
    flipped["p"] = ~flipped["p"]
    out_flipped = transform(flipped)
    np.testing.assert_array_equal(out_flipped["p"], ~out["p"])
    np.testing.assert_array_equal(out_flipped[["x", "y", "t"]], out[["x", "y", "t"]])
    shifted = arr.copy()
    shift = 1_700_000_000_000_000 + 10**12
    shifted["t"] += shift
    out_shifted = transform(shifted)
    np.testing.assert_array_equal(out_shifted["t"] - shift, out["t"])
    np.testing.assert_array_equal(out_shifted[["x", "y", "p"]], out[["x", "y", "p"]])


def test_causal_prefix(rng):
    arr = random_stream(rng, 600, SENSOR, t_max=600)
    transform = EventCount(SENSOR, factor=2, threshold=0.2)
    full = transform(arr)
    cut = 300
    prefix = transform(arr[arr["t"] <= cut])
    np.testing.assert_array_equal(prefix, full[full["t"] <= cut])


def test_burst_at_one_pixel_and_timestamp():
    n = 5000
    burst = np.zeros(n, dtype=DVS_DTYPE)
    burst["x"], burst["y"], burst["t"], burst["p"] = 3, 4, 1_700_000_000_000_000, True
    out = EventCount(SENSOR, factor=2, threshold=0.01)(burst)
    # Region (1, 2) has 4 pixels: a sum of 5000 is a mean of 1250, i.e. 125000 levels of 0.01.
    assert len(out) == 125_000
    assert set(out["x"].tolist()) == {1} and set(out["y"].tolist()) == {2}
    assert out["p"].all() and (out["t"] == 1_700_000_000_000_000).all()


def test_float_timestamps_and_single_event():
    ev = torch.tensor([[2.0, 3.0, 0.125, 1.0], [3.0, 3.0, 0.5, 1.0]], dtype=torch.float64)
    out = EventCount(SENSOR, factor=2, threshold=0.5)(ev)
    assert out.dtype == torch.float64 and out.tolist() == [[1.0, 1.0, 0.5, 1.0]]
    single = np.array([(9, 6, False, 7)], dtype=DVS_DTYPE)
    out = EventCount(SENSOR, factor=(10, 7), threshold=1 / 70)(single)
    assert out.tolist() == [(0, 0, False, 7)]


def test_empty_stream_keeps_kind():
    transform = EventCount(SENSOR, factor=2)
    assert transform(np.empty(0, dtype=DVS_DTYPE)).dtype == DVS_DTYPE
    out = transform(torch.empty(0, 4, dtype=torch.float32))
    assert out.shape == (0, 4) and out.dtype == torch.float32
    assert transform(Events.empty()).num_events == 0


def test_device_and_tensor_kind(device, dtype):
    data = torch.tensor([[0, 0, 10, 1], [1, 1, 20, 1], [0, 1, 30, -1], [1, 0, 40, -1]],
                        device=device, dtype=dtype)
    out = EventCount((2, 2, 2), factor=2, threshold=0.5)(data)
    assert out.device == data.device and out.dtype == dtype
    assert out.tolist() == [[0, 0, 20, 1], [0, 0, 40, -1]]


@pytest.mark.parametrize("threshold", [0.07, 1.0])
def test_streaming_session_equals_whole_stream(threshold, rng):
    arr = random_stream(rng, 3000, SENSOR, t_max=500)  # many equal timestamps
    transform = EventCount(SENSOR, factor=3, threshold=threshold)
    whole = transform(arr)
    cuts = np.sort(rng.choice(np.arange(1, len(arr)), size=12, replace=False))
    session = transform.session()
    parts = [session(chunk) for chunk in np.split(arr, cuts)]
    parts.append(session(np.empty(0, dtype=DVS_DTYPE)))
    np.testing.assert_array_equal(np.concatenate(parts), whole)
    session.reset()
    np.testing.assert_array_equal(session(arr), whole)


def test_streaming_rejects_chunks_out_of_order():
    session = EventCount(SENSOR, factor=2).session()
    session(torch.tensor([[0, 0, 100, 1]]))
    with pytest.raises(ValueError, match="follow each other in time"):
        session(torch.tensor([[0, 0, 99, 1]]))


@pytest.mark.parametrize(
    ("threshold", "error"),
    [(0, ValueError), (-1.0, ValueError), (float("nan"), ValueError), (float("inf"), ValueError),
     ("1", TypeError), (1e-9, ValueError)],
)
def test_bad_threshold(threshold, error):
    with pytest.raises(error, match="threshold"):
        EventCount(SENSOR, factor=2, threshold=threshold)


def test_tonic_compose_on_nmnist(nmnist):
    tonic = pytest.importorskip("tonic")
    sensor = tonic.datasets.NMNIST.sensor_size
    down = EventCount(sensor, factor=4, threshold=0.25)
    window = float(nmnist["t"].max() - nmnist["t"].min() + 1)
    frames = tonic.transforms.Compose(
        [down, tonic.transforms.ToFrame(sensor_size=down.output_sensor_size, time_window=window)]
    )(nmnist)
    out = down(nmnist)
    assert frames.shape == (1, 2, 9, 9) and int(frames.sum()) == len(out)
    assert 0 < len(out) < len(nmnist) and out.dtype == nmnist.dtype
    assert rows(out) == event_count_reference(nmnist, sensor, 4, 0.25)


def test_long_streams_in_chunks_equal_one_pass(rng, monkeypatch):
    import evdown_torch._tensors as common

    arr = random_stream(rng, 2000, SENSOR, t_max=300)
    transform = EventCount(SENSOR, factor=3, threshold=0.2)
    whole = transform(arr)
    monkeypatch.setattr(common, "CHUNK_EVENTS", 37)
    np.testing.assert_array_equal(transform(arr), whole)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    st.lists(
        st.tuples(st.integers(0, 4), st.integers(0, 2), st.integers(0, 20), st.booleans()),
        max_size=60,
    ),
    st.sampled_from([1, 2, 3, (5, 1), (2, 3)]),
    st.sampled_from([0.05, 0.5, 1.0, 1.5]),
)
def test_property_matches_reference_and_flips(rows_in, factor, threshold):
    sensor = (5, 3, 2)
    arr = np.array([(x, y, p, t) for x, y, t, p in rows_in], dtype=DVS_DTYPE)
    transform = EventCount(sensor, factor=factor, threshold=threshold)
    out = transform(arr)
    assert rows(out) == event_count_reference(arr, sensor, factor, threshold)
    flipped = arr.copy()
    flipped["p"] = ~flipped["p"]
    np.testing.assert_array_equal(transform(flipped)["p"], ~out["p"])


@pytest.mark.parametrize("threshold", [0.123457, 3.000001])
@pytest.mark.parametrize("factor", [1, 3])
def test_wide_level_sums_match_the_reference(threshold, factor, rng):
    # Denominators of 10**6: b * S no longer fits int32, so the sums are kept in int64.
    arr = random_stream(rng, 1500, SENSOR, t_max=400, sort=False)
    transform = EventCount(SENSOR, factor=factor, threshold=threshold)
    out = transform(arr)
    assert rows(out) == event_count_reference(arr, SENSOR, factor, threshold)
    session = transform.session()
    in_order = arr[np.argsort(arr["t"], kind="stable")]
    parts = [session(chunk) for chunk in np.array_split(in_order, 5)]
    np.testing.assert_array_equal(np.concatenate(parts), out)


@pytest.mark.parametrize("sensor", [(256, 128, 2), (257, 128, 2)])
def test_region_ids_at_the_edge_of_the_narrow_sort(sensor, rng):
    # 32,768 regions: region ids sorted as int16, the largest one 32,767; one more column of
    # regions: sorted as int32.
    arr = random_stream(rng, 4000, sensor, t_max=40)
    arr["x"][:50] = sensor[0] - 1
    arr["y"][:50] = sensor[1] - 1
    transform = EventCount(sensor, factor=1, threshold=0.5)
    out = transform(arr)
    assert rows(out) == event_count_reference(arr, sensor, 1, 0.5)
    session = transform.session()
    parts = [session(chunk) for chunk in np.array_split(arr, 3)]
    np.testing.assert_array_equal(np.concatenate(parts), out)


def test_move_crossings_from_one_start_per_region_equal_one_per_step(rng):
    from evdown_torch.transforms.functional.reference import move_crossings

    # Steps grouped by region: a random walk of u = M / theta in quarters, per region.
    sizes = rng.integers(1, 40, 25)
    first = np.zeros(sizes.sum(), dtype=bool)
    first[np.cumsum(sizes) - sizes] = True
    u4 = np.cumsum(rng.choice([-3, -1, 1, 2], sizes.sum()))  # 4 * u
    floor_u = torch.as_tensor(np.floor_divide(u4, 4))
    on_level = torch.as_tensor(u4 % 4 == 0)
    q_region = torch.as_tensor(np.floor_divide(u4[first], 4) + rng.integers(0, 2, len(sizes)))
    q_step = torch.zeros(sizes.sum(), dtype=torch.int64)
    q_step[torch.as_tensor(first)] = q_region
    first = torch.as_tensor(first)
    expected = move_crossings(floor_u, on_level, first, q_start=q_step)
    got = move_crossings(floor_u, on_level, first, q_first=q_region)
    assert expected.move.numel() > 0
    for a, b in zip(got, expected):
        assert torch.equal(a, b)


def test_move_crossings_of_steps_that_land_on_every_level_skip_nothing(rng):
    from evdown_torch.transforms.functional.reference import move_crossings

    # Steps of a quarter level (as b * S moves by one against levels of 4): each level the
    # walk reaches, it lands on; only first steps and steps on a level need solving.
    sizes = rng.integers(1, 60, 30)
    first = np.zeros(sizes.sum(), dtype=bool)
    first[np.cumsum(sizes) - sizes] = True
    steps = rng.choice([-1, 1], sizes.sum())
    u4 = np.cumsum(steps)
    floor_u = torch.as_tensor(np.floor_divide(u4, 4))
    on_level = torch.as_tensor(u4 % 4 == 0)
    start_u4 = u4[first] - steps[first]  # the walk just before each region's first step
    q_region = torch.as_tensor(np.floor_divide(start_u4, 4) + (start_u4 % 4 != 0)
                               * rng.integers(0, 2, len(sizes)))
    first = torch.as_tensor(first)
    expected = move_crossings(floor_u, on_level, first, q_first=q_region)
    got = move_crossings(floor_u, on_level, first, q_first=q_region, lands_on_levels=True)
    assert expected.move.numel() > 10
    for a, b in zip(got, expected):
        assert torch.equal(a, b)
