"""calibrate: every budgeted method hits ratio and count targets; the thinning control."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from evdown_torch.events import to_events
from evdown_torch.synthetic import SyntheticGestures
from evdown_torch.transforms import Downsample, EventCount, PhotocurrentPooling
from evdown_torch.transforms.calibrate import BudgetTarget, calibrate, calibration
from evdown_torch.transforms.registry import METHODS
from evdown_torch.transforms.thinning import ThinnedDownsample, recording_seed

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
