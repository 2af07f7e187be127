"""Peak budgets: window rates against slow counts, peak calibration, the limiter after it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdown_torch.synthetic import SyntheticGestures
from evdown_torch.transforms import EventCount, LIFPooling, LinearEstimation, RateLimiter
from evdown_torch.transforms.calibrate import BudgetTarget, calibrate, calibration
from evdown_torch.transforms.window_rates import peak_count, window_rates
from tests.helpers import DVS_DTYPE, FLOAT_DTYPE, random_stream

SENSOR = (48, 48, 2)


@pytest.fixture(scope="module")
def recordings():
    torch.set_num_threads(1)
    data = SyntheticGestures(samples_per_class=1, duration_us=400_000, seed=5,
                             sensor_size=SENSOR)
    return [data[i][0] for i in (0, 4, 9)]


def slow_peak(t, window) -> int:
    """Every window [s, s + W) that starts at an event, counted one by one."""
    t = sorted(t)
    return max((sum(1 for u in t if s <= u < s + window) for s in t), default=0)


def slow_window_counts(t, window) -> list[int]:
    """Counts of [t0 + kW, t0 + (k + 1) W) for k = 0 .. the last event's window."""
    t = sorted(t)
    last = math.floor((t[-1] - t[0]) / window)
    return [sum(1 for u in t if t[0] + k * window <= u < t[0] + (k + 1) * window)
            for k in range(last + 1)]


@pytest.mark.parametrize("window", [1, 7, 100, 2.5])
def test_peak_and_window_counts_against_slow_counts(window, rng):
    parts = [random_stream(rng, n, SENSOR, t_max=t_max) for n, t_max in ((300, 500), (50, 4000))]
    if not float(window).is_integer():
        parts = [p.astype(FLOAT_DTYPE) for p in parts]
    rates = window_rates(parts, window, time_unit="ms")
    counts = sum((slow_window_counts(p["t"].tolist(), window) for p in parts), [])
    assert rates.peak == max(slow_peak(p["t"].tolist(), window) for p in parts)
    assert rates.p99 == pytest.approx(np.percentile(counts, 99))
    spans = sum(float(p["t"].max() - p["t"].min()) for p in parts)
    assert rates.mean == pytest.approx(350 * window / spans)
    assert rates.per_second(rates.peak) == pytest.approx(rates.peak / (window * 1e-3))
    assert peak_count(torch.sort(torch.from_numpy(parts[0]["t"].copy())).values, window) \
        == slow_peak(parts[0]["t"].tolist(), window)


def test_window_rates_of_nothing_are_zero():
    rates = window_rates([np.zeros(0, DVS_DTYPE)], 1000)
    assert (rates.events, rates.mean, rates.p99, rates.peak) == (0, 0.0, 0.0, 0)


@pytest.mark.parametrize("cls", [EventCount, LinearEstimation, LIFPooling])
@pytest.mark.parametrize("max_events", [8, 40])
def test_a_peak_target_is_met_from_below(cls, max_events, recordings):
    target = BudgetTarget.peak(max_events, window=1000)
    found = calibration(cls(SENSOR, 4), recordings, target)
    outputs = [found.transform(r) for r in recordings]
    peak = max(slow_peak(out["t"].tolist(), 1000) for out in outputs)
    assert peak == found.count == found.rates.peak
    assert peak <= max_events
    assert peak >= 0.75 * max_events  # not far below: the search closes in from both sides
    # the busiest windows hold at most R events, so a limiter of R per W drops nothing
    limiter = RateLimiter(max_events, 1000)
    assert all(len(limiter(out)) == len(out) for out in outputs)


def test_the_mean_can_meet_a_rate_while_the_peak_breaks_it(recordings):
    # the DAVIS case in small: a mean rate target says nothing of the busiest window
    found = calibration(EventCount(SENSOR, 4), recordings, BudgetTarget.rate(20_000.0),
                        window=1000)
    rates = found.rates
    assert rates.per_second(rates.mean) == pytest.approx(20_000, rel=0.05)
    assert rates.per_second(rates.peak) > 3 * 20_000
    peak = calibrate(EventCount(SENSOR, 4), recordings, BudgetTarget.peak(20, window=1000))
    assert max(slow_peak(peak(r)["t"].tolist(), 1000) for r in recordings) <= 20


def test_other_targets_report_no_rates_unless_asked(recordings):
    assert calibration(EventCount(SENSOR, 4), recordings, BudgetTarget.ratio(0.1)).rates is None


@pytest.mark.parametrize(("text", "target"), [
    ("ratio=0.05", BudgetTarget.ratio(0.05)),
    ("count=1200", BudgetTarget.count(1200)),
    ("rate=500000", BudgetTarget.rate(500_000.0)),
    ("peak=500000/1ms", BudgetTarget.peak(500, 1000)),
    ("peak = 2e6 / 500us", BudgetTarget.peak(1000, 500)),
    ("peak=10/1s", BudgetTarget.peak(10, 1_000_000)),
])
def test_budget_texts(text, target):
    assert BudgetTarget.parse(text) == target


@pytest.mark.parametrize(("text", "match"), [
    ("ratio", "ratio=R, count=N"), ("speed=3", "ratio=R"), ("peak=500000", "ratio=R"),
    ("rate=5/1ms", "ratio=R"), ("ratio=x", "ratio=R"), ("ratio=-1", "positive"),
    ("peak=500000/1", "number and a unit"), ("peak=500000/ms", "number and a unit"),
    ("peak=1500/1ms", "1.5 events per window"), ("peak=100/1ms", "0.1 events per window"),
    ("peak=0/1ms", "positive"),
])
def test_malformed_budget_texts_say_what_is_wrong(text, match):
    with pytest.raises(ValueError, match=match):
        BudgetTarget.parse(text)


def test_peak_targets_check_their_window():
    with pytest.raises(ValueError, match="needs a window"):
        BudgetTarget("peak", 5)
    with pytest.raises(ValueError, match="window"):
        BudgetTarget.peak(5, 0)
    with pytest.raises(ValueError, match="only to a peak"):
        BudgetTarget("rate", 5.0, window=10)
    with pytest.raises(ValueError, match="rate or peak"):
        BudgetTarget("ratio", 0.1, time_unit=1e-6)
