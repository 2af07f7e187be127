"""Extreme settings of the log-luminance methods: huge and tiny thresholds, huge time spans.

Each case once failed: an ``OverflowError`` for a threshold of 1e300, an allocator crash (or a
run of minutes) for thresholds so small that the output explodes, and wrong crossing times
(an event at INT64_MIN) for streams spanning more than 2**62 microseconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from evdown_torch import CubicEstimation, EventCount, LinearEstimation, max_output_events
from evdown_torch.checks import MAX_EXACT_SPAN
from tests.helpers import DVS_DTYPE, as_tuples, random_stream

LOG_METHODS = [EventCount, LinearEstimation, CubicEstimation]


@pytest.mark.parametrize("method", LOG_METHODS)
@pytest.mark.parametrize("threshold", [1e300, 1e18, 3e9])
def test_a_threshold_no_region_can_reach_gives_no_event(method, threshold):
    one = np.array([(0, 0, True, 0)], DVS_DTYPE)
    assert len(method((4, 4, 2), 2, threshold=threshold)(one)) == 0
    ev = random_stream(np.random.default_rng(0), 500, (6, 6, 2))
    assert len(method((6, 6, 2), 1, threshold=threshold)(ev)) == 0


@pytest.mark.parametrize("method", LOG_METHODS)
def test_a_threshold_just_reachable_still_gives_its_events(method):
    # 1x1 regions, 12 ON events at one pixel then 12 OFF: the level climbs to 12, back to 0.
    ev = np.zeros(24, DVS_DTYPE)
    ev["t"] = np.arange(24) * 10
    ev["p"][:12] = True
    out = method((2, 2, 2), 1, threshold=12.0)(ev)
    assert [bool(p) for p in out["p"]] == [True, False]
    assert len(method((2, 2, 2), 1, threshold=12.5)(ev)) == 0


def test_event_count_session_with_a_huge_threshold_matches_the_batch():
    ev = random_stream(np.random.default_rng(1), 400, (4, 4, 2))
    transform = EventCount((4, 4, 2), 2, threshold=1e300)
    session = transform.session()
    parts = [session(ev[i : i + 100]) for i in range(0, 400, 100)]
    assert sum(len(p) for p in parts) == 0 == len(transform(ev))


def test_event_count_refuses_an_exploding_output_and_names_the_count():
    # Factor 1, threshold 1e-6: every event moves its pixel by exactly 10**6 levels.
    ev = random_stream(np.random.default_rng(2), 20_000, (16, 16, 2))
    with pytest.raises(ValueError, match=r"20,000,000,000 events.*max_output_events\(n\)"):
        EventCount((16, 16, 2), 1, threshold=1e-6)(ev)


def test_the_output_limit_counts_the_whole_call():
    ev = random_stream(np.random.default_rng(3), 1000, (8, 8, 2))
    transform = EventCount((8, 8, 2), 1, threshold=1.0)  # factor 1, theta 1: a copy
    assert len(transform(ev)) == 1000
    with max_output_events(999), pytest.raises(
        ValueError, match="1,000 events, more than the limit of 999"
    ):
        transform(ev)
    with max_output_events(1000):
        assert as_tuples(transform(ev)) == as_tuples(ev)


@pytest.mark.usefixtures("kernels")
def test_the_limit_counts_every_chunk_of_a_long_stream(monkeypatch):
    import evdown_torch._tensors as tensors

    monkeypatch.setattr(tensors, "CHUNK_EVENTS", 100)  # ten chunks of 100 events
    ev = random_stream(np.random.default_rng(4), 1000, (8, 8, 2))
    with max_output_events(950), pytest.raises(ValueError, match="more than the limit of 950"):
        EventCount((8, 8, 2), 1, threshold=1.0)(ev)


@pytest.mark.parametrize("method", [LinearEstimation, CubicEstimation])
def test_estimators_refuse_an_exploding_output_before_building_it(method):
    # 300 events at threshold 1e-6 ask for tens of millions of crossings: counted, refused.
    ev = random_stream(np.random.default_rng(0), 300, (8, 8, 2), t_max=100_000)
    with max_output_events(1_000_000), pytest.raises(
        ValueError, match=r"would hold at least [\d,]+ events"
    ):
        method((8, 8, 2), 2, threshold=1e-6)(ev)
    with max_output_events(1_000_000):
        small = method((8, 8, 2), 2, threshold=1e-3)(ev)  # ~50k events: within the limit
    assert 10_000 < len(small) < 1_000_000


def _two_pixel_ramp(t0: int, span: int) -> np.ndarray:
    # Pixel (0, 0) ON at t0, pixel (1, 0) ON at t0 + span: the 2x1 region's mean rises as a
    # line from 1/2 to 1, so at threshold 1/4 it crosses 1/4 and 1/2 at t0, 3/4 halfway, 1 at
    # the end (the linear and cubic curves coincide: every pixel has two knots).
    return np.array([(0, 0, True, t0), (1, 0, True, t0 + span)], DVS_DTYPE)


@pytest.mark.parametrize("method", [LinearEstimation, CubicEstimation])
@pytest.mark.parametrize("span", [10**6, 10**11, MAX_EXACT_SPAN - 2])
def test_spans_below_2_53_are_computed_and_shift_exactly_at_any_clock_offset(method, span):
    transform = method((2, 1, 2), (2, 1), threshold=0.25)
    base = transform(_two_pixel_ramp(0, span))
    assert base["p"].all()
    got = base["t"].tolist()
    assert got[:2] == [0, 0] and got[3] == span
    # Halfway to within the documented rounding tolerance (32 * 2**-53 of the piece, a tick).
    assert abs(got[2] - span // 2) <= 32 * 2.0**-53 * span + 1
    if span <= 10**11:
        assert got[2] == span // 2
    for t0 in (2**62, -(2**62), 12_345):
        shifted = transform(_two_pixel_ramp(t0, span))
        assert (shifted["t"] - t0).tolist() == got


@pytest.mark.parametrize("method", [LinearEstimation, CubicEstimation])
@pytest.mark.parametrize("k", [10**6, 10**12, 10**13])
def test_long_pieces_round_to_the_nearest_tick(method, k):
    # Threshold 1/6: the region's sum 1 + s crosses 4/3 at s = 1/3 and 5/3 at s = 2/3 of a
    # piece of 3k + 1 ticks, at k + 1/3 and 2k + 2/3: rounded to k and 2k + 1. The half-tick
    # nudge follows the float error (a fixed 1e-12 of the piece moved them 3 to 30 ticks).
    span = 3 * k + 1
    out = method((2, 1, 2), (2, 1), threshold=1 / 6)(_two_pixel_ramp(-(2**60), span))
    assert (out["t"] + 2**60).tolist() == [0] * 3 + [k, 2 * k + 1, span]
    assert out["p"].all()


@pytest.mark.parametrize("method", [LinearEstimation, CubicEstimation])
@pytest.mark.parametrize("span", [MAX_EXACT_SPAN, 2**62 + 7, 2**63 - 1, 2**63, 2**64 - 1])
def test_spans_the_arithmetic_cannot_hold_are_refused(method, span):
    # Spans of 2**63 and more wrap in int64 (t_end - t_start < 0): refused all the same, in
    # one call, in a batch and in a session, with the span measured exactly.
    t0 = -(2**63) if span >= 2**63 else -(2**62) if span > 2**62 else 0
    ev = _two_pixel_ramp(t0, span)
    message = rf"span {span:,} .* 2\*\*53"
    transform = method((2, 1, 2), (2, 1), threshold=0.25)
    with pytest.raises(ValueError, match=message):
        transform(ev)
    with pytest.raises(ValueError, match=message):
        transform.batch([ev[:1], ev])
    session = method((2, 1, 2), (2, 1), threshold=0.25, max_delay=10).session()
    session(ev[:1])
    with pytest.raises(ValueError, match=message):
        session(ev[1:])


def test_float_timestamps_have_no_span_limit():
    ev = np.array([(0, 0, True, 0.0), (1, 0, True, 1e17)],
                  dtype=[("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<f8")])
    out = LinearEstimation((2, 1, 2), (2, 1), threshold=0.25)(ev)
    assert out["t"].tolist() == [0.0, 0.0, 5e16, 1e17]
