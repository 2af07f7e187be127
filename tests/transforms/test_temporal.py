"""TemporalFunnelling (method 8) against a slow reference, hand-computed cases, invariants."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdown_torch import Chain, EventCount, Events, TemporalFunnelling
from evdown_torch.transforms.functional import temporal_funnelling
from tests.helpers import DVS_DTYPE, random_stream, rows, temporal_reference

SENSOR = (8, 6, 2)

# Every test on both CPU paths: the compiled loop and the eager kernel.
pytestmark = pytest.mark.usefixtures("kernels")


def test_hand_computed_bins_and_repeats():
    # t_start 100, dt 50: bins [100, 150), [150, 200), [200, 250).
    ev = torch.tensor([[1, 1, 100, 1], [1, 1, 149, 1], [1, 1, 149, 0], [2, 1, 150, 1],
                       [1, 1, 230, 1], [2, 1, 199, 1]])
    out = TemporalFunnelling(dt=50)(ev)
    assert out.tolist() == [[1, 1, 100, 1], [1, 1, 100, 0], [2, 1, 150, 1], [1, 1, 200, 1]]


@pytest.mark.parametrize("dt", [1, 7, 250, 10**9])
def test_matches_the_reference_on_random_streams(dt, rng):
    arr = random_stream(rng, 2000, SENSOR, t_max=3000, sort=False)
    out = TemporalFunnelling(dt=dt, sensor_size=SENSOR)(arr)
    assert out.dtype == arr.dtype
    assert rows(out) == temporal_reference(arr, dt)


def test_float_timestamps_bin_in_float(rng):
    ev = torch.tensor([[0, 0, 0.25, 1], [0, 0, 0.5, 1], [0, 0, 0.75, 1]], dtype=torch.float64)
    assert TemporalFunnelling(dt=0.5)(ev).tolist() == [[0, 0, 0.25, 1], [0, 0, 0.75, 1]]


def test_dt_one_only_drops_exact_repeats():
    arr = np.array([(0, 0, True, 3), (0, 0, True, 3), (0, 0, True, 4)], dtype=DVS_DTYPE)
    assert rows(TemporalFunnelling(dt=1)(arr)) == [(0, 0, 3, True), (0, 0, 4, True)]


def test_shifting_the_clock_shifts_the_output_exactly(rng):
    arr = random_stream(rng, 500, SENSOR, t_max=1000)
    shifted = arr.copy()
    shifted["t"] += 2**62 - 10**4
    base = TemporalFunnelling(dt=33)(arr)
    moved = TemporalFunnelling(dt=33)(shifted)
    np.testing.assert_array_equal(moved["t"] - (2**62 - 10**4), base["t"])
    np.testing.assert_array_equal(moved[["x", "y", "p"]], base[["x", "y", "p"]])


def test_empty_input_gives_empty_output_of_the_same_kind():
    out = TemporalFunnelling(dt=10)(torch.zeros((0, 4), dtype=torch.int16))
    assert out.shape == (0, 4) and out.dtype == torch.int16
    assert temporal_funnelling(Events.empty(), dt=3).num_events == 0


@pytest.mark.parametrize(("dt", "error"), [(0, ValueError), (-1, ValueError),
                                           (math.inf, ValueError), ("5", TypeError)])
def test_bad_dt_is_refused(dt, error):
    with pytest.raises(error, match="dt"):
        TemporalFunnelling(dt=dt)


def test_fractional_dt_is_refused_for_integer_timestamps():
    with pytest.raises(ValueError, match="whole number"):
        TemporalFunnelling(dt=2.5)(torch.tensor([[0, 0, 1, 1]]))


@pytest.mark.parametrize("dt", [2**63 - 1, 2**63, 1e19, 2**64, 1e300])
def test_a_dt_beyond_every_int64_span_is_one_bin(dt):
    # Offsets from the first t reach 2**62 + 5 < dt: every event lies in the first bin.
    ev = torch.tensor([[0, 0, 5, 1], [0, 0, 9, 1], [1, 0, 2**62 + 10, 1], [0, 0, 2**62, 0]])
    assert TemporalFunnelling(dt=dt)(ev).tolist() == [[0, 0, 5, 1], [0, 0, 5, 0],
                                                       [1, 0, 5, 1]]
    session = TemporalFunnelling(dt=dt).session()
    assert session(ev[:2]).tolist() == [[0, 0, 5, 1]]
    assert session(ev[2:]).tolist() == [[0, 0, 5, 0], [1, 0, 5, 1]]


def test_integer_timestamps_spanning_2_to_the_63_are_refused():
    ev = torch.tensor([[0, 0, -(2**62), 1], [0, 0, 2**62, 1]])
    with pytest.raises(ValueError, match=r"span 2\*\*63 or more"):
        TemporalFunnelling(dt=10)(ev)


def test_coordinates_are_checked_against_the_sensor_when_given():
    with pytest.raises(ValueError):
        TemporalFunnelling(dt=5, sensor_size=(2, 2, 2))(torch.tensor([[2, 0, 1, 1]]))


def test_input_is_not_modified(rng):
    arr = random_stream(rng, 100, SENSOR, t_max=50)
    copy = arr.copy()
    TemporalFunnelling(dt=10)(arr)
    np.testing.assert_array_equal(arr, copy)


def test_composes_with_a_spatial_method_in_tonic_and_in_a_chain(rng):
    tonic = pytest.importorskip("tonic")
    arr = random_stream(rng, 1000, SENSOR, t_max=2000)
    count = EventCount(SENSOR, factor=2, threshold=0.5)
    temporal = TemporalFunnelling(dt=40)
    composed = tonic.transforms.Compose([temporal, count])(arr)
    np.testing.assert_array_equal(Chain(temporal, count)(arr), composed)
    np.testing.assert_array_equal(composed, count(temporal(arr)))
    assert set(np.unique(composed["t"] - arr["t"][0]) % 40) <= {0}
