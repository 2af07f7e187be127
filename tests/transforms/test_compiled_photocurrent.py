"""PhotocurrentPooling's compiled CPU loop (events mode) against its eager kernel and the slow
float64 reference."""

from __future__ import annotations

import decimal
import importlib
import inspect
import math

import numpy as np
import pytest
import torch

from evdown_torch import Events, PhotocurrentPooling, eager_kernels
from evdown_torch.transforms.functional.photocurrent.events_mode import photocurrent_events
from evdown_torch.transforms.functional.photocurrent.method import (
    photocurrent_events_init,
    photocurrent_events_step,
)
from evdown_torch.transforms.functional.photocurrent.settings import PhotocurrentState
from evdown_torch.transforms.functional.reference import SNAP
from tests.helpers import (
    DVS_DTYPE,
    FLOAT_DTYPE,
    argument_spy,
    assert_identical,
    assert_output_limit_on_both_paths,
    assert_sessions_on_both_paths,
    both_paths,
    near_their_limits,
    photocurrent_events_reference,
    random_stream,
    rows,
    spy,
)

pytest.importorskip("numba")

COMPILED = importlib.import_module("evdown_torch.transforms.functional.compiled.photocurrent")
EAGER = importlib.import_module("evdown_torch.transforms.functional.photocurrent.events_mode")

SENSOR = (10, 7, 2)
FACTORS = [1, 2, 3, (2, 3), (3, 1), (4, 3), (10, 7)]  # (3, 1), (4, 3): not dividing
CONTRASTS = [(0.2, None), (0.2, 0.05), (0.5, 0.3), (1.5, 0.7), (0.01, 0.004)]

#: Test streams squeezed into a few microseconds: the rate check's warning is expected.
DENSE_TIMES = pytest.mark.filterwarnings("ignore::evdown_torch.time_units.TimeUnitWarning")


@pytest.fixture
def compiled_calls(monkeypatch) -> list[bool]:
    """Per call of the compiled step: whether it decided the call (False: the eager kernel)."""
    return spy(monkeypatch, COMPILED, "photocurrent_step", lambda out: out is not None)


def _check(transform: PhotocurrentPooling, arr: np.ndarray, calls: list[bool]) -> np.ndarray:
    """The transform on both paths: identical, equal to the reference, decided compiled."""
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    s = transform.settings
    assert rows(compiled) == photocurrent_events_reference(
        arr, s.sensor_size, s.factor, s.contrast, s.output_threshold)
    assert calls and all(calls)  # no call was left to the eager kernel
    return compiled


@pytest.mark.parametrize("factor", FACTORS)
@pytest.mark.parametrize(("contrast", "threshold"), CONTRASTS)
def test_compiled_equals_eager_and_the_reference(factor, contrast, threshold, rng,
                                                  compiled_calls):
    arr = random_stream(rng, 1200, SENSOR, t_max=300, sort=False)
    transform = PhotocurrentPooling(SENSOR, factor=factor, contrast=contrast,
                                    threshold=threshold)
    _check(transform, arr, compiled_calls)


def test_the_compiled_loop_runs_and_the_eager_kernel_does_not(monkeypatch, rng,
                                                              compiled_calls):
    pieces = spy(monkeypatch, EAGER, "_anchored_piece")
    arr = random_stream(rng, 100, SENSOR)
    PhotocurrentPooling(SENSOR, factor=2)(arr)
    assert (compiled_calls, len(pieces)) == ([True], 0)
    with eager_kernels():
        PhotocurrentPooling(SENSOR, factor=2)(arr)
    assert (compiled_calls, len(pieces)) == ([True], 1)


@DENSE_TIMES
@pytest.mark.parametrize("dtype", [np.int64, np.float32, np.float64])
def test_timestamp_dtypes_near_their_limits(dtype, rng):
    arr = random_stream(rng, 800, SENSOR, t_max=50, sort=False)
    data = near_their_limits(arr, dtype, 50)
    transform = PhotocurrentPooling(SENSOR, factor=(3, 2), contrast=0.2, threshold=0.05)
    compiled, eager = both_paths(lambda: transform(data))
    assert_identical(compiled, eager)
    assert compiled.dtype == data.dtype and len(compiled) > 0
    if dtype == np.int64:
        assert int(compiled[:, 2].min()) >= 2**63 - 60
        expected = photocurrent_events_reference(arr, SENSOR, (3, 2), 0.2, 0.05)
        assert [tuple(r) for r in compiled[:, [0, 1, 3]].tolist()] == [
            (x, y, 1 if on else -1) for x, y, _, on in expected]


@DENSE_TIMES
def test_float64_structured_timestamps(rng, compiled_calls):
    arr = random_stream(rng, 600, SENSOR, t_max=200, dtype=FLOAT_DTYPE, sort=False)
    arr["t"] = arr["t"] * 1e-6 + 1.7e9  # seconds since 1970, in float64
    _check(PhotocurrentPooling(SENSOR, factor=2, contrast=0.3), arr, compiled_calls)


@pytest.mark.parametrize(("factor", "contrast", "threshold"), [((3, 2), 0.2, 0.05),
                                                                ((4, 3), 1.5, 0.7), (1, 0.3, None)])
def test_sessions_in_odd_chunks_and_moving_between_paths(factor, contrast, threshold, rng):
    arr = random_stream(rng, 1500, SENSOR, t_max=200)
    transform = PhotocurrentPooling(SENSOR, factor=factor, contrast=contrast,
                                    threshold=threshold)
    whole, _ = both_paths(lambda: transform(arr))
    assert rows(whole) == photocurrent_events_reference(arr, SENSOR, factor, contrast,
                                                        transform.threshold)
    assert_sessions_on_both_paths(transform, arr, whole)


@pytest.mark.parametrize("n", [1, 4])
def test_one_step_gives_the_same_state_object_on_both_paths(n, rng):
    settings = PhotocurrentPooling(SENSOR, factor=(4, 3), contrast=0.3, threshold=0.1).settings
    events = Events.from_columns(*(torch.as_tensor(c)[:n] for c in (
        [1, 9, 2, 2], [0, 6, 1, 1], [5, 6, 7, 7], [True, False, True, True])))
    fresh = photocurrent_events_init(settings, events)
    levels = torch.as_tensor(rng.integers(-20, 20, fresh.level.shape[0]))
    state = PhotocurrentState(levels, fresh.reference + 2, torch.tensor(4))  # a resumed stream
    before = [column.clone() for column in state]
    compiled, eager = both_paths(lambda: photocurrent_events_step(events, state, settings))
    assert_identical(compiled[0], eager[0])
    assert isinstance(compiled[1], PhotocurrentState) and isinstance(eager[1], PhotocurrentState)
    assert_identical(tuple(compiled[1]), tuple(eager[1]))
    assert_identical(list(state), before)  # the given state is not written


def test_batches_sorted_stacked_and_with_empty_recordings(rng):
    transform = PhotocurrentPooling(SENSOR, factor=(3, 2), contrast=0.25, threshold=0.1)
    recordings = [random_stream(rng, n, SENSOR, t_max=100) for n in (50, 0, 300, 1, 120)]
    unsorted = [random_stream(rng, n, SENSOR, t_max=100, sort=False) for n in (80, 0, 200)]
    for batch in (recordings, unsorted):
        compiled, eager = both_paths(lambda batch=batch: transform.batch(batch))
        assert_identical(compiled, eager)
        for recording, out in zip(batch, compiled, strict=True):
            assert rows(out) == photocurrent_events_reference(recording, SENSOR, (3, 2), 0.25,
                                                              0.1)


def test_many_crossings_per_event_grow_the_output(rng, compiled_calls):
    # c / theta = 30 at factor 1: each event crosses 30 levels, far past the first buffer.
    arr = random_stream(rng, 3000, SENSOR, t_max=1000)
    out = _check(PhotocurrentPooling(SENSOR, factor=1, contrast=1.5, threshold=0.05), arr,
                 compiled_calls)
    assert len(out) >= 30 * 3000


@pytest.mark.parametrize("limit", [1, 299, 5_000])
def test_the_output_limit_raises_the_same_error_and_keeps_the_session(limit, rng):
    arr = random_stream(rng, 300, (8, 8, 2), t_max=50)
    transform = PhotocurrentPooling((8, 8, 2), factor=1, contrast=1.0, threshold=0.05)
    message = assert_output_limit_on_both_paths(transform, arr, limit, 20 * 290)
    assert "more than the limit" in message


def _hot_pixel(rng, n_on, sensor, n_rest, *, fall=False):
    """One pixel going ``n_on`` times ON (or OFF), then random events elsewhere."""
    hot = np.zeros(n_on, dtype=DVS_DTYPE)
    hot["t"] = np.arange(n_on) * 2
    hot["p"] = not fall
    rest = random_stream(rng, n_rest, sensor, t_max=2 * n_on)
    return np.sort(np.concatenate([hot, rest]), order="t", kind="stable")


@pytest.mark.parametrize(("contrast", "threshold", "fall"), [
    (0.25, 0.4, False),  # climbs 150 log units: anchored again and again
    (0.5, 0.3, True),  # falls 300: the sum drops far below its anchor
    (45.0, 20.0, False),  # one level is more than the headroom
    (20.0, 5.0, True),  # pixels too dark to count
])
def test_climbing_and_falling_regions(contrast, threshold, fall, rng, compiled_calls):
    arr = _hot_pixel(rng, 600, (4, 4, 2), 1500, fall=fall)
    _check(PhotocurrentPooling((4, 4, 2), factor=2, contrast=contrast, threshold=threshold), arr,
           compiled_calls)


def test_levels_spanning_more_than_the_table(compiled_calls):
    # c = 1e-4: the levels a sum can hold span more than the table, so each intensity takes
    # an exp; 70,000 ON at one pixel of a 2x1 region, then the other goes down twice.
    n = 70_000
    arr = np.zeros(n + 2, dtype=DVS_DTYPE)
    arr["t"] = np.arange(n + 2)
    arr["p"][:n] = True
    arr["x"][n:] = 1
    assert COMPILED._intensities(1e-4, 2)[0].shape[0] == 0  # no table
    out = _check(PhotocurrentPooling((2, 1, 2), factor=(2, 1), contrast=1e-4, threshold=1e-3),
                 arr, compiled_calls)
    assert len(out) > 500


def test_factor_one_at_theta_equal_to_c_returns_the_input(rng, compiled_calls):
    arr = random_stream(rng, 1000, SENSOR, t_max=300)
    out = _check(PhotocurrentPooling(SENSOR, factor=1, contrast=0.2), arr, compiled_calls)
    assert_identical(out, arr)


def test_a_whole_region_on_a_level_is_decided_compiled(compiled_calls):
    # Every pixel of a 2x2 region ON once: u = c / theta = 1 exactly, on the level.
    arr = np.zeros(4, dtype=DVS_DTYPE)
    arr["x"], arr["y"], arr["t"], arr["p"] = [0, 1, 0, 1], [0, 0, 1, 1], [1, 2, 3, 4], True
    out = _check(PhotocurrentPooling((2, 2, 2), factor=2, contrast=0.3), arr, compiled_calls)
    assert rows(out) == [(0, 0, 4, True)]


def test_an_event_near_a_snap_bound_is_left_to_the_eager_kernel(compiled_calls):
    # theta = c / (1 + 1e-9): after one ON at factor 1, u = 1 + 1e-9, on the snap bound.
    arr = np.array([(0, 0, True, 5), (1, 0, True, 6)], dtype=DVS_DTYPE)
    transform = PhotocurrentPooling((2, 1, 2), factor=1, contrast=0.5,
                                    threshold=0.5 / (1 + 1e-9))
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert compiled_calls == [False]


@pytest.mark.parametrize("delta", [-1.5e-9, -5e-10, 5e-10, 1.5e-9])
@pytest.mark.parametrize("factor", [1, (2, 1)])
def test_events_just_inside_and_just_past_a_level_bound(delta, factor, compiled_calls):
    # theta = c / (1 + delta): a region's u reaches 1 + delta and -(1 + delta), within a few
    # SNAP (1e-9) of the bounds 1 - SNAP and -1 + SNAP that move q; only delta = -1.5e-9
    # stays inside them (q never moves). Every u lies 5e-10 or more from a snap bound, clear
    # of the two paths' doubt (2e-10 here): the loop decides every call.
    if factor == 1:  # u = (1 + delta) L at pixel 0: L = 1, 0, -1, 0
        xs, ons, moves = [0, 0, 0, 0], [True, False, False, True], [(1, True), (2, False),
                                                                     (3, False), (4, True)]
    else:  # u = log((e^(c L0) + e^(c L1)) / 2) / theta: about 0.53, 1 + delta, 0.53, 0, ...
        xs, ons = [0, 1, 1, 0, 0, 1], [True, True, False, False, False, False]
        moves = [(2, True), (4, False), (6, False)]  # ..., -0.47, -(1 + delta)
    arr = np.zeros(len(xs), dtype=DVS_DTYPE)
    arr["x"], arr["t"], arr["p"] = xs, np.arange(1, len(xs) + 1), ons
    transform = PhotocurrentPooling((2, 1, 2), factor=factor, contrast=0.5,
                                    threshold=0.5 / (1 + delta))
    out = _check(transform, arr, compiled_calls)
    assert [(t, on) for _, _, t, on in rows(out)] == ([] if delta < -1e-9 else moves)


def _exact_u(total: int, anchor: int, log_n: float, contrast: float, threshold: float,
             bits: int) -> decimal.Decimal:
    """``u`` of a region's sum ``total`` in fixed point (``2**bits``) against ``anchor``,
    to 40 digits."""
    d = decimal.Decimal
    with decimal.localcontext(decimal.Context(prec=40)):
        log_v = (d(total) / d(2) ** bits).ln()
        return (d(contrast) * anchor - d(log_n) + log_v) / d(threshold)


@pytest.mark.parametrize(("anchor", "q", "n_r", "contrast", "threshold"), [
    (0, 0, 1, 0.5, 0.5), (3, 0, 16, 0.2, 0.3), (-40, -30, 12, 0.2, 0.3), (7, 3, 1156, 1.5, 2.0),
    (2_000, 199_990, 16, 0.01, 1e-4), (-500, -166, 9, 0.2, 0.6), (900, 361, 4, 0.4, 1.0),
])
def test_stay_bounds_hold_u_inside_the_bounds_that_move_q(anchor, q, n_r, contrast,
                                                          threshold):
    # The sums strictly between low and high keep q for both paths: their exact u lies inside
    # q +- (1 - SNAP) by the slack (both error bounds, in log units over theta), and the bounds
    # give away little more than that (the sums just outside come within 1e-9 log units).
    bits = COMPILED._intensities(contrast, n_r)[3]
    slack = COMPILED._stay_slack(n_r, bits, threshold)
    low, high = np.empty(1, np.int64), np.empty(1, np.int64)
    COMPILED._stay_bounds(0, np.array([anchor]), np.array([q]), np.array([math.log(n_r)]),
                          contrast, threshold, 2.0**bits, slack, low, high)
    lowest, highest = 1 << (bits - COMPILED.DROP_BITS), n_r << (bits + COMPILED.HEADROOM_BITS)
    assert lowest <= low[0] + 1 < high[0] - 1 <= highest  # the region's sums can reach both

    def u(total):
        return _exact_u(int(total), anchor, math.log(n_r), contrast, threshold, bits)

    inside = decimal.Decimal(slack / threshold)
    tight = decimal.Decimal(slack / threshold + 1e-9 / threshold)
    top, bottom = q + 1 - decimal.Decimal(SNAP), q - 1 + decimal.Decimal(SNAP)
    assert u(high[0] - 1) < top - inside and u(high[0]) > top - tight
    assert u(low[0] + 1) > bottom + inside and u(low[0]) < bottom + tight


def test_the_doubt_test_against_hand_computed_values():
    bits = 50
    exact, doubtful = 2**bits, round(2**bits * math.exp(1e-9))  # u = 1, 1 + 1e-9
    assert COMPILED._u_and_doubt(2, exact, 0.0, 1, 0.5, 1.0, 2.0**bits) == (1.0, False)
    u, doubt = COMPILED._u_and_doubt(2, doubtful, 0.0, 1, 0.5, 1.0, 2.0**bits)
    assert abs(u - (1 + 1e-9)) < 1e-14 and doubt
    # u = 1.4: far from both bounds; at theta = 1e-6 the eager bound exceeds SNAP: in doubt.
    assert not COMPILED._u_and_doubt(0, round(2**bits * math.exp(0.7)), 0.0, 1, 0.5, 0.5,
                                     2.0**bits)[1]
    assert COMPILED._u_and_doubt(2, exact, 0.0, 1, 1e-6, 2e-6, 2.0**bits)[1]


def test_an_event_outside_the_sensor_is_an_error_not_a_crash():
    events = Events.from_columns([0, 12], [0, 1], [1, 2], [True, True])
    with eager_kernels(False), pytest.raises(
            ValueError, match=r"event 1 at \(x=12, y=1\) lies outside the sensor of 10 x 7"):
        photocurrent_events(events, sensor_size=SENSOR, factor=(3, 2), contrast=0.2,
                            threshold=0.2)


def _one_pixel_falling_below_the_table(n_off: int) -> np.ndarray:
    """A 2x1 region: pixel 0 ON once (the anchor), then pixel 1 OFF ``n_off`` times."""
    arr = np.zeros(n_off + 1, dtype=DVS_DTYPE)
    arr["t"] = np.arange(n_off + 1)
    arr["p"][0] = True
    arr["x"][1:] = 1
    return arr


@DENSE_TIMES
@pytest.mark.parametrize("contrast, threshold, stream", [
    (0.2, 0.05, "hot"),  # the table, most events kept between the stay bounds
    (0.5, 0.3, "falling"),  # pixels falling below the table's lowest level (intensity 0)
    (20.0, 5.0, "falling"),  # pixels too dark to count
    (1e-4, 1e-3, "hot"),  # no table: an exp per intensity
    (0.5, 0.3, "below"),  # one pixel steps below the table, its region never anchored again
])
def test_each_region_sum_is_its_pixels_intensities_exactly(contrast, threshold, stream, rng,
                                                           monkeypatch):
    # The loop moves a region's sum by each event's change of intensity; after the call each
    # anchored region's sum must equal its pixels' intensities above its anchor, rounded one
    # by one (the module's telescoping), whatever path each event took.
    parameters = inspect.signature(COMPILED._photocurrent_loop.py_func)
    seen = argument_spy(monkeypatch, COMPILED, "_photocurrent_loop")
    if stream == "below":
        sensor, factor, arr = (2, 1, 2), (2, 1), _one_pixel_falling_below_the_table(200)
    else:
        sensor, factor = (4, 4, 2), (2, 2)
        arr = _hot_pixel(rng, 600, sensor, 1500, fall=stream == "falling")
    with eager_kernels(False):
        PhotocurrentPooling(sensor, factor=factor, contrast=contrast, threshold=threshold)(arr)
    assert len(seen) == 1  # the compiled loop decided the call
    args = parameters.bind(*seen[0]).arguments
    level, anchor, total, ready = args["level"], args["anchor"], args["total"], args["ready"]
    table, lo, scale = args["table"], args["lo"], args["scale"]

    def intensity(j: int) -> int:
        if j < lo:
            return 0
        return int(table[j - lo]) if len(table) else math.floor(math.exp(contrast * j) * scale
                                                                 + 0.5)

    width, height, _ = sensor
    fx, fy = factor
    out_w = width // fx
    checked = 0
    for r in np.flatnonzero(ready):
        ry, rx = divmod(int(r), out_w)
        pixels = [y * width + x for y in range(fy * ry, fy * ry + fy)
                  for x in range(fx * rx, fx * rx + fx)]
        assert int(total[r]) == sum(intensity(int(level[p]) - int(anchor[r])) for p in pixels)
        checked += 1
    assert checked > 0
    if stream == "below":  # the anchor pixel alone counts; the other is far below the table
        assert int(level[1]) - int(anchor[0]) < lo and int(total[0]) == intensity(0)
