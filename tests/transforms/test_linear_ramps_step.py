"""LinearEstimation's compiled session step through the ramps (compiled/linear_stream.py).

A bounded-delay linear session with int64 timestamps on the CPU steps each chunk through the
ramps; its outputs, chunk by chunk, must be the eager session's (same events, same order,
same dtypes), its state the package's (a session moves between the paths at any chunk), and
the settings the ramps cannot hold must go to the windowed session with the same events.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import torch

from evdown_torch import LinearEstimation, eager_kernels, max_output_events
from evdown_torch.events import Events
from evdown_torch.transforms.functional.estimation.settings import EstimationSettings
from evdown_torch.transforms.functional.estimation.stream import (
    estimation_finish,
    estimation_init,
    estimation_step,
)
from tests.helpers import assert_identical, random_stream

pytest.importorskip("numba")
from evdown_torch.transforms.functional.compiled import linear_stream  # noqa: E402
from evdown_torch.transforms.functional.compiled.linear_ramps import RampSession  # noqa: E402

#: (sensor, factor, threshold, max_delay, time span, first time): factors that do not divide
#: the sensor, non-square ones, thresholds down to 0.05 and above 1, delays from 1 us, a
#: clock near the int64 limit.
CASES = [
    ((34, 34, 2), (4, 4), 0.25, 1000, 60_000, 0),
    ((9, 7, 2), (2, 3), 0.05, 7, 3_000, 0),
    ((9, 7, 2), (3, 2), 1.5, 300, 30_000, 0),
    ((5, 3, 2), (2, 2), 0.3, 1, 500, 0),
    ((8, 6, 2), (4, 4), 0.25, 1000, 40_000, 2**62 - 100_000),
]


def _events(arr: np.ndarray) -> Events:
    return Events.from_columns(arr["x"].astype(np.int64), arr["y"].astype(np.int64),
                               arr["t"].astype(np.int64), arr["p"])


def _stream(case: tuple, seed: int, n: int = 3000) -> np.ndarray:
    sensor, _, _, _, span, first = case
    arr = random_stream(np.random.default_rng(seed), n, sensor, t_max=span)
    arr["t"] += first
    return arr


def _steps(events: Events, bounds: list[int], settings: EstimationSettings, *, eager: bool,
           ) -> list[Events | None]:
    state, outputs = None, []
    with eager_kernels(eager):
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
            out, state = estimation_step(events.part(lo, hi), state, settings)
            outputs.append(out)
        outputs.append(estimation_finish(state, settings))
    return outputs


@pytest.fixture
def ramp_calls(monkeypatch) -> list:
    """Each chunk the ramps' session reads (its length)."""
    seen, real = [], RampSession.__call__

    def wrapper(self, x, *args):
        seen.append(len(x))
        return real(self, x, *args)

    monkeypatch.setattr(RampSession, "__call__", wrapper)
    return seen


@pytest.mark.parametrize("case", range(len(CASES)))
def test_ramps_give_the_eager_sessions_events_chunk_by_chunk(case, ramp_calls):
    sensor, factor, threshold, delay, _, _ = CASES[case]
    settings = EstimationSettings(sensor, factor, threshold, max_delay=delay, curve="linear")
    for seed in range(12):
        events = _events(_stream(CASES[case], seed))
        rng = np.random.default_rng(seed)
        cuts = rng.integers(1, events.num_events, 30).tolist()  # ties cut, one-event chunks
        bounds = sorted({0, events.num_events, *cuts, *(c + 1 for c in cuts[:5])})
        calls = len(ramp_calls)
        compiled = _steps(events, bounds, settings, eager=False)
        assert len(ramp_calls) - calls == len(bounds) - 1  # every chunk through the ramps
        eager = _steps(events, bounds, settings, eager=True)
        assert_identical(compiled, eager)
        assert sum(o.num_events for o in eager if o is not None) > 20


def test_a_transform_session_moving_between_paths_gives_the_batch_events(ramp_calls):
    arr = random_stream(np.random.default_rng(3), 20_000, (34, 34, 2), t_max=200_000)
    transform = LinearEstimation((34, 34, 2), factor=4, threshold=0.2, max_delay=500)
    session = transform.session()
    rng = np.random.default_rng(4)
    parts = []
    for chunk in np.array_split(arr, 40):
        with eager_kernels(bool(rng.random() < 0.4)):
            parts.append(session(chunk))
    parts.append(session.flush())
    assert ramp_calls
    with eager_kernels(True):
        expected = transform(arr)
    np.testing.assert_array_equal(np.concatenate(parts), expected)


#: A Tonic array's fields with int64 timestamps.
INT_DTYPE = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")])


def _batch_and_session(transform, arr: np.ndarray, cut: int, *, first_eager: bool):
    """The eager batch call on ``arr``, and a session over ``arr[:cut]`` on the eager path (or
    the compiled one) then ``arr[cut:]`` and the flush on the compiled path, concatenated."""
    with eager_kernels(True):
        expected = transform(arr)
    session = transform.session()
    with eager_kernels(first_eager):
        parts = [session(arr[:cut])]
    with eager_kernels(False):
        parts += [session(arr[cut:]), session.flush()]
    return expected, np.concatenate(parts)


def test_a_seeded_session_counts_every_ramp_of_a_merged_knot(ramp_calls):
    # Found by a differential search. Pixel (0, 10)'s first knot merges two events (a change
    # of -2) and starts at t_start; the eager state holds it as one knot. The ramps' session
    # seeded from that state put one entry in its starts ring, which the sweep counted as one
    # active ramp while the knot's end took two away: the ramp from t = 2 to 12 then counted
    # none, its rounding went unbounded, and a crossing at t = 7 came out twice.
    arr = np.array([(10, 7, 1, True), (0, 10, 2, False), (0, 10, 2, False), (0, 10, 12, False),
                    (9, 15, 25, True)], dtype=INT_DTYPE)
    transform = LinearEstimation((19, 23, 2), factor=1, threshold=0.05, max_delay=17)
    expected, out = _batch_and_session(transform, arr, 4, first_eager=True)
    assert len(ramp_calls) == 1  # the second chunk, seeded from the eager state
    assert_identical(out, expected)
    assert [int(t) for t in expected["t"][expected["x"] == 0]].count(7) == 2


@pytest.mark.parametrize("first_eager", [True, False])
def test_more_crossings_than_the_ramps_buffer_take_the_window(first_eager, ramp_calls):
    # Found by a differential search (19,435 events on a 4 x 4 sensor within 4 us). The
    # ramps size their outputs' buffer for one pixel level a change of their rings; 200 ON
    # events of one pixel at one time (a knot of change 200, over a threshold of 0.05) cross
    # 1,340-odd levels at once. That chunk used to raise "the output buffer is too small";
    # now the windowed step solves it, from the state the ramps never wrote.
    arr = np.array([(0, 0, 0, True)] * 200 + [(3, 3, 10, False)], dtype=INT_DTYPE)
    transform = LinearEstimation((4, 4, 2), factor=(1, 3), threshold=0.05, max_delay=3)
    expected, out = _batch_and_session(transform, arr, 200, first_eager=first_eager)
    assert ramp_calls  # the ramps took a chunk and gave it up
    assert_identical(out, expected)
    assert len(expected) > 1300


def test_a_state_stepped_twice_gives_the_same_events_both_times(ramp_calls):
    # The ramps' session kept beside a state is taken by the first step on it; a second step
    # on the same state seeds a session from the state's tensors.
    settings = EstimationSettings((9, 7, 2), (2, 2), 0.3, max_delay=40, curve="linear")
    events = _events(_stream(CASES[1], 0, 600))
    _, state = estimation_step(events.part(0, 300), None, settings)
    first, after_first = estimation_step(events.part(300, 600), state, settings)
    second, after_second = estimation_step(events.part(300, 600), state, settings)
    assert_identical(first, second)
    assert_identical(estimation_finish(after_first, settings),
                     estimation_finish(after_second, settings))
    assert len(ramp_calls) == 3


@pytest.mark.parametrize(
    ("change", "taken"),
    [
        (dict(threshold=1e8), False),  # levels too wide for the fixed point
        (dict(threshold=1e6), True),  # no event but the first level's
        (dict(max_delay=linear_stream.MAX_RAMP_DELAY + 1), False),
        (dict(max_delay=linear_stream.MAX_RAMP_DELAY), True),
        (dict(curve="cubic"), False),
    ],
)
def test_settings_the_ramps_cannot_hold_take_the_windowed_session(change, taken, ramp_calls):
    base = dict(sensor_size=(9, 7, 2), factor=(2, 2), threshold=0.3, max_delay=40,
                curve="linear")
    settings = EstimationSettings(**{**base, **change})
    events = _events(_stream(CASES[1], 1, 500))
    bounds = [0, 200, 500]
    compiled = _steps(events, bounds, settings, eager=False)
    assert bool(ramp_calls) == taken
    assert_identical(compiled, _steps(events, bounds, settings, eager=True))


def test_float_timestamps_and_levels_beyond_the_headroom_take_the_windowed_session(
        ramp_calls, monkeypatch):
    settings = EstimationSettings((9, 7, 2), (2, 2), 0.3, max_delay=40, curve="linear")
    arr = _stream(CASES[1], 2, 500)
    floats = Events.from_columns(arr["x"].astype(np.int64), arr["y"].astype(np.int64),
                                 arr["t"].astype(np.float64), arr["p"])
    _steps(floats, [0, 500], settings, eager=False)
    assert not ramp_calls
    # A region whose level changes, the state's and the chunk's, could leave half the
    # headroom (here 4 pixels * 2**4 levels): that chunk takes the windowed session, and the
    # next the ramps again, seeded from the windowed session's state.
    monkeypatch.setattr(linear_stream, "LEVEL_BITS", 5)
    rng = np.random.default_rng(5)
    arr = random_stream(rng, 150, (9, 7, 2), t_max=3000)
    arr["x"][:] = rng.integers(0, 2, 150)
    arr["y"][:] = rng.integers(0, 2, 150)  # all in region (0, 0)
    arr["p"][:] = np.arange(150) % 2 == 0
    events = _events(arr)
    bounds = [0, 40, 140, 150]
    compiled = _steps(events, bounds, settings, eager=False)
    assert ramp_calls[0] == 40 and 100 not in ramp_calls and ramp_calls[-1] == 10
    assert_identical(compiled, _steps(events, bounds, settings, eager=True))


def test_an_event_outside_the_sensor_is_refused_and_the_state_kept(ramp_calls):
    settings = EstimationSettings((9, 7, 2), (2, 2), 0.3, max_delay=40, curve="linear")
    events = _events(_stream(CASES[1], 3, 400))
    _, state = estimation_step(events.part(0, 200), None, settings)
    knots = state.knots.t.clone()
    bad = events.part(200, 400)
    y = bad.y.clone()
    y[17] = 7
    with pytest.raises(ValueError, match=r"event 17 at \(x=\d+, y=7\) lies outside the sensor "
                                         r"of 9 x 7 pixels"):
        estimation_step(Events(bad.x, y, bad.t, bad.p), state, settings)
    assert torch.equal(state.knots.t, knots)
    out, _ = estimation_step(bad, state, settings)
    with eager_kernels():
        expected, _ = estimation_step(bad, state, settings)
    assert_identical(out, expected)


def test_the_output_limit_is_applied_to_a_step():
    settings = EstimationSettings((9, 7, 2), (1, 1), 0.05, max_delay=40, curve="linear")
    events = _events(_stream(CASES[1], 4, 400))
    with eager_kernels(False), max_output_events(10), pytest.raises(ValueError,
                                                                    match="more than the limit"):
        estimation_step(events, None, settings)
    with eager_kernels(False):
        out, _ = estimation_step(events, None, settings)
    assert out.num_events > 10


def test_levels_fit_region_by_region(monkeypatch):
    # Room: 4 pixels * 2**4 = 64 level changes a region (9 x 7 sensor, factor 2: 20 regions).
    monkeypatch.setattr(linear_stream, "LEVEL_BITS", 5)
    settings = EstimationSettings((9, 7, 2), (2, 2), 0.3, max_delay=40, curve="linear")
    ramps = linear_stream.ramp_settings((9, 7, 2), (2, 2), Fraction(3, 10), 40)
    x, y = np.meshgrid(np.arange(9), np.arange(7))
    spread_x, spread_y = np.tile(x.ravel(), 4), np.tile(y.ravel(), 4)  # 252, at most 16 each
    state = estimation_init(settings, _events(_stream(CASES[1], 0, 10)))
    assert linear_stream._levels_fit(spread_x, spread_y, state, ramps)
    one_region = np.zeros(64, np.int64)
    assert not linear_stream._levels_fit(one_region, one_region, state, ramps)
    assert linear_stream._levels_fit(one_region[:63], one_region[:63], state, ramps)
    # The state's knots count with their whole levels.
    ons = Events.from_columns([0, 1, 0, 8], [0, 1, 0, 6], [0, 100, 190, 200], [1, 1, 1, 1])
    _, state = estimation_step(ons, None, settings)
    carried = int(state.change[(state.knots.x < 2) & (state.knots.y < 2)].abs().sum())
    assert carried > 0
    assert not linear_stream._levels_fit(one_region[: 64 - carried], one_region[: 64 - carried],
                                         state, ramps)


@pytest.mark.parametrize("case", [0, 2])
def test_ramps_sessions_keep_the_flip_and_shift_invariants(case, ramp_calls):
    # docs/semantics.md: flipping every polarity flips every output's; adding a constant to
    # every t adds it to every output t, exactly, at any int64 clock. Through the ramps alone.
    sensor, factor, threshold, delay, _, _ = CASES[case]
    transform = LinearEstimation(sensor, factor=factor, threshold=threshold, max_delay=delay)
    arr = _stream(CASES[case], 11)

    def session_of(stream: np.ndarray) -> np.ndarray:
        session = transform.session()
        with eager_kernels(False):
            parts = [session(chunk) for chunk in np.array_split(stream, 9)]
        return np.concatenate([*parts, session.flush()])

    out = session_of(arr)
    assert len(ramp_calls) == 9 and len(out) > 20
    flipped = arr.copy()
    flipped["p"] = ~flipped["p"]
    out_flipped = session_of(flipped)
    np.testing.assert_array_equal(out_flipped[["x", "y", "t"]], out[["x", "y", "t"]])
    np.testing.assert_array_equal(out_flipped["p"], ~out["p"])
    for shift in (1_700_000_000_000_000, 2**62 - 10**6 - int(arr["t"].max())):
        moved = arr.copy()
        moved["t"] += shift
        out_moved = session_of(moved)
        np.testing.assert_array_equal(out_moved["t"] - shift, out["t"])
        np.testing.assert_array_equal(out_moved[["x", "y", "p"]], out[["x", "y", "p"]])
