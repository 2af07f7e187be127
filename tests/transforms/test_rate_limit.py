"""RateLimiter: against a slow token bucket, session == batch, composition, the block loop."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from evdown_torch import Chain, EventCount, Events
from evdown_torch.transforms import RateLimiter
from evdown_torch.transforms.functional import rate_limit as kernel
from evdown_torch.transforms.functional.rate_limit import limit_rate
from tests.helpers import DVS_DTYPE, FLOAT_DTYPE, random_stream, rows, spy

SENSOR = (8, 6, 2)


def bucket_reference(times, max_events: int, window) -> list[bool]:
    """Event by event, in exact fractions: refill ``R * gap / W`` (capped at ``R``), then an
    event passes when a whole token is there and takes it."""
    level, last, keep = Fraction(max_events), None, []
    for t in times:
        t = Fraction(t)
        if last is not None:
            level = min(Fraction(max_events), level + max_events * (t - last) / Fraction(window))
        last = t
        keep.append(level >= 1)
        if keep[-1]:
            level -= 1
    return keep


def bursty_stream(rng, n: int, window: int, dtype=DVS_DTYPE) -> np.ndarray:
    """Bursts (gaps of 0 or 1) between quiet stretches (gaps up to 3 windows), sorted."""
    gaps = np.where(rng.random(n) < 0.8, rng.integers(0, 2, n), rng.integers(0, 3 * window, n))
    out = np.zeros(n, dtype=dtype)
    out["x"], out["y"] = rng.integers(0, SENSOR[0], n), rng.integers(0, SENSOR[1], n)
    out["t"], out["p"] = np.cumsum(gaps), rng.random(n) < 0.5
    return out


def limited_reference(arr: np.ndarray, max_events: int, window) -> list[tuple]:
    order = np.argsort(arr["t"], kind="stable")
    ordered = arr[order]
    keep = bucket_reference(ordered["t"].tolist(), max_events, window)
    return [row for row, kept in zip(rows(ordered), keep, strict=True) if kept]


def test_hand_computed_bucket():
    # R = 2 per W = 4: a token every 2 us, at most 2 held. t=0: 2 -> pass, pass, drop (0
    # left); t=1: 0.5, drop; t=2: 1, pass; t=5: 1.5, pass; t=6: 1, pass; t=20: full (2).
    ev = torch.tensor([[0, 0, t, 1] for t in (0, 0, 0, 1, 2, 5, 6, 20, 20, 20)])
    out = RateLimiter(max_events=2, window=4)(ev)
    assert out[:, 2].tolist() == [0, 0, 2, 5, 6, 20, 20]


@pytest.mark.parametrize(("max_events", "window"), [(1, 1), (1, 7), (3, 10), (5, 4), (8, 1000)])
def test_matches_the_reference_on_bursty_streams(max_events, window, rng):
    arr = bursty_stream(rng, 5000, window)
    out = RateLimiter(max_events, window, sensor_size=SENSOR)(arr)
    assert out.dtype == arr.dtype
    assert rows(out) == limited_reference(arr, max_events, window)
    assert 0 < len(out) < len(arr)  # the streams do overflow


def test_unsorted_input_is_taken_in_stable_time_order(rng):
    arr = random_stream(rng, 3000, SENSOR, t_max=2000, sort=False)
    assert rows(RateLimiter(3, 5)(arr)) == limited_reference(arr, 3, 5)


def test_many_overflow_episodes_over_long_blocks(rng):
    # Long full stretches (blocks double past the first 256 events) and hundreds of
    # overflows, in one call and in a session of uneven chunks.
    n = 40_000
    gaps = np.where((np.arange(n) // 300) % 2 == 0, 1, 0)  # 300 events at rate 1, 300 at once
    arr = np.zeros(n, dtype=DVS_DTYPE)
    arr["t"] = np.cumsum(gaps) + rng.integers(0, 2, n).cumsum()
    limiter = RateLimiter(max_events=50, window=60)
    out = limiter(arr)
    assert rows(out) == limited_reference(arr, 50, 60)
    session = limiter.session()
    bounds = [0, *sorted(rng.choice(np.arange(1, n), 40, replace=False).tolist()), n]
    parts = [session(arr[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]
    assert np.array_equal(np.concatenate(parts + [session.flush()]), out)


def test_float_timestamps_on_a_binary_grid_match_the_exact_reference(rng):
    # Multiples of 1/8 with a window of 2.5: every float64 step of the kernel is exact.
    arr = bursty_stream(rng, 4000, 20, dtype=FLOAT_DTYPE)
    arr["t"] = arr["t"] / 8
    out = RateLimiter(max_events=3, window=2.5)(arr)
    assert out["t"].dtype == np.float64
    assert rows(out) == limited_reference(arr, 3, 2.5)


def chunkings(rng, n: int):
    """Odd chunkings of ``n`` events: singles, a cut at every tie, random cuts with empties."""
    yield [(i, i + 1) for i in range(n)]
    yield [(0, n)]
    for _ in range(3):
        cuts = sorted(rng.integers(0, n + 1, 12).tolist())  # repeats: empty chunks
        bounds = [0, *cuts, n]
        yield list(zip(bounds[:-1], bounds[1:]))


@pytest.mark.parametrize("float_times", [False, True])
def test_session_equals_the_call_whatever_the_chunks(float_times, rng):
    arr = bursty_stream(rng, 600, 12, dtype=FLOAT_DTYPE if float_times else DVS_DTYPE)
    if float_times:  # irregular floats: not on any grid
        arr["t"] = arr["t"] * 0.37 + rng.random(len(arr)).cumsum() * 1e-3
    limiter = RateLimiter(max_events=4, window=3.3 if float_times else 12)
    whole = limiter(arr)
    for chunks in chunkings(rng, len(arr)):
        session = limiter.session()
        parts = [session(arr[a:b]) for a, b in chunks]
        dropped = session.state.dropped if session.state is not None else 0
        parts.append(session.flush())
        assert np.array_equal(np.concatenate(parts), whole)
        assert dropped == len(arr) - len(whole)


def test_empty_input_and_empty_chunks():
    limiter = RateLimiter(max_events=2, window=10)
    out = limiter(torch.zeros((0, 4), dtype=torch.int16))
    assert out.shape == (0, 4) and out.dtype == torch.int16
    assert limit_rate(Events.empty(), max_events=1, window=1).num_events == 0
    session = limiter.session()
    assert len(session(np.zeros(0, DVS_DTYPE))) == 0
    assert len(session.flush()) == 0


@given(times=st.lists(st.integers(0, 60), min_size=1, max_size=80),
       max_events=st.integers(1, 5), window=st.integers(1, 15))
@settings(max_examples=150, deadline=None)
def test_any_stream_matches_the_reference(times, max_events, window):
    times = sorted(times)
    ev = torch.tensor([[0, 0, t, 1] for t in times])
    out = RateLimiter(max_events, window)(ev)
    keep = bucket_reference(times, max_events, window)
    assert out[:, 2].tolist() == [t for t, kept in zip(times, keep, strict=True) if kept]


def test_no_interval_passes_more_than_the_bucket_allows(rng):
    arr = bursty_stream(rng, 3000, 40)
    t = RateLimiter(max_events=7, window=40)(arr)["t"]
    # events in [t_i, t_j] <= R + R (t_j - t_i) / W, for every pair
    for i in range(0, len(t), 13):
        span = t[i:] - t[i]
        count = np.arange(1, len(span) + 1)
        assert (count <= 7 + 7 * span / 40 + 1e-9).all()
    # so a window [s, s + W) holds at most 2 R - 1
    busiest = max(int(((t >= s) & (t < s + 40)).sum()) for s in t)
    assert busiest <= 2 * 7 - 1


def test_a_stream_within_the_peak_loses_nothing(rng):
    # Every window [s, s + W) holds at most R events: the bucket never runs dry.
    t = np.sort(rng.choice(np.arange(0, 100_000, 25), 3000, replace=False))  # >= 25 apart
    arr = np.zeros(len(t), dtype=DVS_DTYPE)
    arr["t"] = t
    assert len(RateLimiter(max_events=4, window=100)(arr)) == len(arr)


def test_the_loop_runs_per_episode_not_per_event(monkeypatch, rng):
    # 100,000 events with 5 bursts: a few dozen blocks, each a handful of torch passes.
    n = 100_000
    arr = np.zeros(n, dtype=DVS_DTYPE)
    gaps = np.full(n, 10)
    for start in rng.choice(n - 2000, 5, replace=False):
        gaps[start:start + 1000] = 0
    arr["t"] = np.cumsum(gaps)
    full = spy(monkeypatch, kernel, "_full_block")
    overflow = spy(monkeypatch, kernel, "_overflow_block")
    out = RateLimiter(max_events=100, window=1000)(arr)
    assert rows(out) == limited_reference(arr, 100, 1000)
    assert len(full) + len(overflow) < 80, (len(full), len(overflow))


def test_on_the_device(device, dtype, rng):
    arr = bursty_stream(rng, 2000, 9)
    ev = torch.from_numpy(np.stack([arr["x"], arr["y"], arr["t"], arr["p"]], 1).astype(
        np.int64)).to(device=device, dtype=dtype)
    out = RateLimiter(max_events=3, window=9)(ev)
    assert out.device == ev.device
    assert out[:, 2].cpu().tolist() == [r[2] for r in limited_reference(arr, 3, 9)]


def test_composes_after_a_method_in_a_chain_and_tonic(rng):
    arr = random_stream(rng, 4000, (32, 32, 2), t_max=20_000)
    method = EventCount((32, 32, 2), factor=4, threshold=0.25)
    chain = Chain(method, RateLimiter(max_events=5, window=500,
                                      sensor_size=method.output_sensor_size))
    expected = RateLimiter(5, 500)(method(arr))
    assert np.array_equal(chain(arr), expected)
    session = chain.session()
    parts = [session(c) for c in np.array_split(arr, 17)] + [session.flush()]
    assert np.array_equal(np.concatenate(parts), expected)
    tonic = pytest.importorskip("tonic")
    composed = tonic.transforms.Compose([method, RateLimiter(5, 500)])
    assert np.array_equal(composed(arr), expected)


@pytest.mark.parametrize(("kwargs", "error", "match"), [
    ({"max_events": 0, "window": 5}, ValueError, "max_events"),
    ({"max_events": 2.5, "window": 5}, TypeError, "max_events"),
    ({"max_events": 2, "window": 0}, ValueError, "window"),
    ({"max_events": 2, "window": math.inf}, ValueError, "window"),
    ({"max_events": 2, "window": "5"}, TypeError, "window"),
])
def test_bad_settings_are_refused(kwargs, error, match):
    with pytest.raises(error, match=match):
        RateLimiter(**kwargs)


def test_integer_timestamps_need_a_whole_window_and_a_countable_rate():
    ev = torch.tensor([[0, 0, 5, 1]])
    with pytest.raises(ValueError, match="whole number"):
        RateLimiter(2, 2.5)(ev)
    with pytest.raises(ValueError, match="2\\*\\*52"):
        RateLimiter(2**31 - 1, 2**31 - 3)(ev)
    assert RateLimiter(2, 2.5)(ev.double()).shape == (1, 4)  # floats take any window
