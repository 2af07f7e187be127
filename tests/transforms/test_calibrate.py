"""calibrate: every budgeted method hits ratio, count and peak targets; window rates against
slow counts; the limiter after a peak calibration; the thinning control."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from evdown_torch.events import to_events
from evdown_torch.synthetic import SyntheticGestures
from evdown_torch.transforms import (
    Downsample,
    EventCount,
    LIFPooling,
    LinearEstimation,
    PhotocurrentPooling,
    RateLimiter,
)
from evdown_torch.transforms.calibrate import BudgetTarget, calibrate, calibration
from evdown_torch.transforms.registry import METHODS
from evdown_torch.transforms.thinning import ThinnedDownsample, recording_seed
from evdown_torch.transforms.window_rates import peak_count, window_rates
from tests.helpers import DVS_DTYPE, FLOAT_DTYPE, random_stream

SENSOR = (48, 48, 2)
BUDGETED = [name for name, cls in METHODS.items() if cls.budget_setting is not None]
#: Tonic's filters reach only some counts (Decimation keeps 1 in n per pixel; RefractoryPeriod
#: keeps at least each pixel's first event): tests/transforms/test_tonic_peers.py checks that
#: calibrate takes the closest.
COARSE = ("refractory", "decimation")


@pytest.fixture(scope="module")
def recordings():
    torch.set_num_threads(1)
    data = SyntheticGestures(samples_per_class=1, duration_us=400_000, seed=5,
                             sensor_size=SENSOR)
    return [data[i][0] for i in (0, 4, 9)]


def _total(transform, recordings):
    return sum(len(transform(r)) for r in recordings)


def test_every_budgeted_method_is_found():
    assert {"event_count", "linear", "cubic", "lif"} <= set(BUDGETED)
    assert METHODS["downsample"].budget_setting is None


@pytest.mark.parametrize("name", [n for n in BUDGETED if n not in COARSE])
@pytest.mark.parametrize("factor", [2, 4])
def test_ratio_and_count_targets_within_5_percent(name, factor, recordings):
    inputs = sum(len(r) for r in recordings)
    camera = METHODS[name](SENSOR, factor)
    for target, wanted in ((BudgetTarget.ratio(0.04), 0.04 * inputs),
                           (BudgetTarget.count(0.15 * inputs), 0.15 * inputs)):
        found = calibration(camera, recordings, target)
        assert found.target == pytest.approx(wanted)
        out = _total(found.transform, recordings)
        assert out == found.count
        assert abs(out - wanted) <= 0.05 * wanted, (name, factor, target, out, wanted)
        # only the budget setting changed
        setting = type(camera).budget_setting
        assert dataclasses.replace(found.transform, **{setting: getattr(camera, setting)}) \
            == camera


def test_calibrate_is_deterministic_and_leaves_the_transform(recordings):
    down = EventCount(SENSOR, 2, threshold=1.0)
    a = calibrate(down, recordings, BudgetTarget.ratio(0.1))
    b = calibrate(down, recordings, BudgetTarget.ratio(0.1))
    assert a == b and down.threshold == 1.0 and a.threshold != 1.0


def test_rate_target(recordings):
    seconds = sum((r["t"].max() - r["t"].min()) * 1e-6 for r in recordings)
    found = calibration(EventCount(SENSOR, 4), recordings, BudgetTarget.rate(800.0))
    assert found.target == pytest.approx(800.0 * seconds)
    assert abs(found.count - found.target) <= 0.05 * found.target


def test_unreachable_target_gives_the_closest(recordings):
    # the control cannot keep more than every event
    inputs = sum(len(r) for r in recordings)
    found = calibration(ThinnedDownsample(SENSOR, 2), recordings, BudgetTarget.ratio(3.0))
    assert found.transform.keep == 1.0 and found.count == inputs


def test_a_count_reachable_only_at_the_end_of_the_range_is_reached():
    # 60 ON events of one pixel. PhotocurrentPooling with factor 1 and threshold == contrast
    # returns its input exactly: 60 events at threshold 1e-6, the smallest allowed; any larger
    # threshold needs more than one input step per output event, so fewer come out. The
    # widening steps by 4 from 1e-3 (to 2.4e-7, outside the range) must try 1e-6 itself.
    ev = torch.tensor([[1, 2, 10 * i, 1] for i in range(60)])
    camera = PhotocurrentPooling((4, 4, 2), 1, contrast=1e-6, threshold=1e-3)
    found = calibration(camera, [ev], BudgetTarget.count(60))
    assert found.value == 1e-6 and found.count == 60
    # the same at the top of a range: keep = 1 keeps every one of Downsample's events
    found = calibration(ThinnedDownsample((4, 4, 2), 1, keep=0.3), [ev],
                        BudgetTarget.ratio(1.0))
    assert found.value == 1.0 and found.count == 60


def test_bad_calibrations(recordings):
    with pytest.raises(ValueError, match="no budget setting"):
        calibrate(Downsample(SENSOR, 2), recordings, BudgetTarget.ratio(0.1))
    with pytest.raises(TypeError, match=r"got 0\.25: give BudgetTarget\.ratio\(r\) .*"
                       r"e\.g\. BudgetTarget\.ratio\(0\.25\)"):
        calibrate(EventCount(SENSOR, 2), recordings, 0.25)
    with pytest.raises(TypeError, match=r"BudgetTarget\.ratio\(0\.1\)"):
        calibrate(EventCount(SENSOR, 2), recordings, "10%")
    with pytest.raises(ValueError, match="target"):
        BudgetTarget.ratio(-1.0)
    empty = recordings[0][:0]
    with pytest.raises(ValueError, match="at least one event"):
        calibrate(EventCount(SENSOR, 2), [empty], BudgetTarget.ratio(0.1))


def test_control_keeps_its_budget(recordings):
    inputs = sum(len(r) for r in recordings)
    control = calibrate(ThinnedDownsample(SENSOR, 4), recordings, BudgetTarget.ratio(0.2))
    assert abs(_total(control, recordings) - 0.2 * inputs) <= 0.05 * 0.2 * inputs
    assert 0.18 < control.keep < 0.22
    for r in recordings:
        out = control(r)
        down = Downsample(SENSOR, 4)(r)
        # a subset of Downsample's events, in order, the same on every call
        assert np.array_equal(out, control(r))
        keys = set(map(tuple, down.tolist()))
        assert all(tuple(e) in keys for e in out.tolist())
        assert abs(len(out) - control.keep * len(down)) < 4 * np.sqrt(len(down))


def test_control_is_seeded_by_the_recording(recordings):
    control = ThinnedDownsample(SENSOR, 2, keep=0.5)
    first = control(recordings[0])
    tensor = torch.as_tensor(np.stack([recordings[0][k].astype(np.int64)
                                       for k in ("x", "y", "t", "p")], 1))
    assert np.array_equal(control(tensor).numpy()[:, 2], first["t"])
    assert recording_seed(to_events(recordings[0])[0]) != recording_seed(
        to_events(recordings[1])[0])
    assert not np.array_equal(ThinnedDownsample(SENSOR, 2, keep=0.5, seed=1)(recordings[0]),
                              first)
    with pytest.raises(ValueError, match="keep"):
        ThinnedDownsample(SENSOR, 2, keep=1.5)
    with pytest.raises(NotImplementedError, match="seeded by the whole recording"):
        control.session()


def _same(a, b):
    return all(torch.equal(u, v) for u, v in zip(a, b))


def test_thinning_draws_equal_one_control_per_seed():
    g = torch.Generator().manual_seed(3)
    n = 5000
    ev = torch.stack([torch.randint(0, 16, (n,), generator=g), torch.randint(0, 8, (n,),
                      generator=g), torch.sort(torch.randint(0, 10**6, (n,), generator=g))[0],
                      torch.randint(0, 2, (n,), generator=g)], 1)
    control = ThinnedDownsample((16, 8, 2), 2, keep=0.3)
    events = to_events(ev, (16, 8, 2))[0]
    draws = control.draws(events, [0, 4, 9])
    for seed, out in zip([0, 4, 9], draws):
        assert _same(out, dataclasses.replace(control, seed=seed).kernel(events))
    assert not _same(draws[0], draws[1])  # each seed its own thinning
    everything = dataclasses.replace(control, keep=1.0)
    for out in everything.draws(events, [0, 1]):
        assert _same(out, everything.kernel(events)) and out.num_events == n


def test_integer_and_float_recordings_together_are_refused_up_front(monkeypatch):
    from tests.helpers import FLOAT_DTYPE, random_stream

    ints = random_stream(np.random.default_rng(0), 300, (8, 8, 2), t_max=10_000)
    floats = random_stream(np.random.default_rng(1), 300, (8, 8, 2), t_max=10_000
                           ).astype(FLOAT_DTYPE)
    runs: list[int] = []
    real = EventCount.batch
    monkeypatch.setattr(EventCount, "batch", lambda self, r: runs.append(1) or real(self, r))
    with pytest.raises(ValueError, match="calibration recordings: .*all have integer or all "
                                         "float timestamps; got both"):
        calibrate(EventCount((8, 8, 2), 2), [ints, floats], BudgetTarget.ratio(0.1))
    assert runs == []  # nothing was run
    for same in ([ints, ints], [floats, floats]):  # one clock: calibrated as before
        calibrate(EventCount((8, 8, 2), 2), same, BudgetTarget.ratio(0.1))


def test_only_the_output_limit_counts_as_too_many_events(monkeypatch):
    import importlib

    kernel = importlib.import_module("evdown_torch.transforms.functional.event_count")
    from tests.helpers import random_stream

    ev = random_stream(np.random.default_rng(2), 300, (8, 8, 2), t_max=10_000)

    def broken(*args, **kwargs):
        raise ValueError("a kernel's own complaint")

    monkeypatch.setattr(kernel, "event_count_batch", broken)
    with pytest.raises(ValueError, match="a kernel's own complaint"):  # not "always inf"
        calibrate(EventCount((8, 8, 2), 2), [ev], BudgetTarget.ratio(0.1))


# --- peak budgets and window rates ---------------------------------------------------------


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
