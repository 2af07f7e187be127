"""LIFPooling against the SpikingPooling module on dense frames, hand-computed cases, invariants."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from evdown_torch import Events, LIFPooling, max_output_events
from evdown_torch.models import SpikingPooling
from evdown_torch.transforms import calibrate_weight
from tests.helpers import (
    DVS_DTYPE,
    LIF_CASES,
    LIF_SETTINGS,
    as_tuples,
    assert_shift_equivariant,
    bursty_stream,
    lif_case,
    lif_dense_reference,
    random_stream,
)


@pytest.fixture(params=["as chosen", "closed form on every call"])
def lif_path(request) -> list[bool] | None:
    """Run a test with the kernel's own choice of path (``None``), then with the closed form
    tried on every call (the list of its answers, see ``tests/conftest.py``)."""
    if request.param == "as chosen":
        return None
    return request.getfixturevalue("lif_closed_form_answers")


@pytest.mark.parametrize("settings", LIF_SETTINGS)
@pytest.mark.parametrize(("sensor", "factor"), [((8, 6, 2), 2), ((9, 7, 2), (4, 3))])
def test_matches_module_on_dense_frames(settings, sensor, factor, rng):
    for _ in range(3):
        arr = bursty_stream(rng, 6, sensor, gap_max=120)
        pool = LIFPooling(sensor, factor, dt=7, **settings)
        assert as_tuples(pool(arr)) == lif_dense_reference(arr, pool)


@pytest.mark.parametrize("reset", ["subtract", "zero", "none"])
@pytest.mark.parametrize("tau", [math.inf, 20.0, 10.0 / math.log(2)])  # beta 1, 0.6065, 0.5
def test_skipping_empty_steps_equals_stepping_through_them(reset, tau, lif_path):
    # A burst leaves the membrane far above threshold, then nothing happens for many steps:
    # with snntorch's delayed reset the neuron keeps firing into the silence (subtract: one
    # threshold per step; none: while it decays; zero: never). The kernel skips the silence.
    sensor = (4, 4, 2)
    burst = [(x, y, True, t) for t in range(3) for x in range(2) for y in range(2)]
    late = [(3, 3, False, 900), (0, 0, True, 905), (1, 0, True, 2000)]
    arr = np.array(burst + late, dtype=DVS_DTYPE)
    pool = LIFPooling(sensor, 2, dt=10, tau=tau, weight=0.7, reset_mechanism=reset)
    out = pool(arr)
    assert as_tuples(out) == lif_dense_reference(arr, pool)
    fired_in_silence = out["t"][(out["t"] > 10) & (out["t"] < 900)]
    # 12 events * 0.7 = 8.4 after step 0 (t = 10); the silence spans steps 1 to 88 (t < 900).
    # subtract: U_j = beta U_{j-1} - 1 fires while > 1 (beta 1: 7.4, ..., 1.4; beta 0.61: 4.09,
    # 1.48; beta 0.5: 3.2); none: 8.4 beta^j > 1 (beta 1: every step; 0.61: j <= 4; 0.5: j <= 3).
    beta = 1.0 if tau == math.inf else round(math.exp(-10 / tau), 2)
    expected = {
        "subtract": {1.0: 7, 0.61: 2, 0.5: 1},
        "zero": {1.0: 0, 0.61: 0, 0.5: 0},
        "none": {1.0: 88, 0.61: 4, 0.5: 3},
    }[reset][beta]
    assert len(fired_in_silence) == expected
    np.testing.assert_array_equal(fired_in_silence, 20 + 10 * np.arange(expected))
    assert lif_path is None or lif_path  # the closed form was tried


def test_integrate_and_fire_limit_on_events(lif_path):
    # factor 2 (n = 4), no leak, weight 1/4, threshold 1, one ON event per step in block (0, 0):
    # snntorch fires when the membrane exceeds 1, so at the 5th event (step 4), then every 4.
    events = [(k % 2, (k // 2) % 2, True, 100 * k + 3) for k in range(19)]
    arr = np.array(events, dtype=DVS_DTYPE)
    out = LIFPooling((4, 4, 2), 2, dt=100, tau=math.inf, weight=0.25)(arr)
    assert out.tolist() == [(0, 0, True, 3 + 100 * (k + 1)) for k in (4, 8, 12, 16)]
    assert lif_path is None or lif_path  # the closed form was tried


def test_mutual_inhibition_cancels_balanced_events(rng):
    on = random_stream(rng, 500, (8, 8, 2), t_max=5000)
    on["p"] = True
    off = on.copy()
    off["p"] = False
    off["x"] ^= 1  # the neighbouring pixel: same 2x2 block, same time
    arr = np.sort(np.concatenate([on, off]), order="t", kind="stable")
    pool = LIFPooling((8, 8, 2), 2, dt=50, tau=400.0, weight=0.5)
    assert len(pool(arr)) > 0
    assert len(dataclasses.replace(pool, mutual_inhibition=0.5)(arr)) == 0


@pytest.mark.parametrize(
    "dtype",
    [
        DVS_DTYPE,
        np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "<i1")]),  # -1/+1
        np.dtype([("x", "<i8"), ("y", "<i8"), ("t", "<f8"), ("p", "<u1")]),
    ],
)
def test_output_in_sensor_sorted_same_kind(dtype, rng):
    sensor = (30, 20, 2)
    arr = random_stream(rng, 3000, sensor, t_max=20_000, dtype=dtype, sort=False)
    before = arr.copy()
    pool = LIFPooling(sensor, (4, 3), dt=100, tau=500.0, weight=0.4)
    out = pool(arr)
    np.testing.assert_array_equal(arr, before)
    assert out.dtype == arr.dtype and len(out) > 0
    w, h, _ = pool.output_sensor_size
    assert (w, h) == (8, 7)
    assert out["x"].min() >= 0 and out["x"].max() < w and out["y"].min() >= 0
    assert out["y"].max() < h
    assert np.all(np.diff(out["t"]) >= 0)
    assert set(np.unique(out["p"]).tolist()) <= set(np.unique(arr["p"]).tolist())
    assert out["t"].min() > arr["t"].min() and out["t"].max() <= arr["t"].max()


def test_tensor_and_events_inputs(device, rng):
    sensor = (16, 16, 2)
    arr = random_stream(rng, 2000, sensor, t_max=30_000)
    pool = LIFPooling(sensor, 4, dt=200, tau=1000.0, weight=0.5)
    expected = pool(arr)
    assert len(expected) > 0
    columns = [np.ascontiguousarray(arr[name]) for name in ("x", "y", "t", "p")]
    tensor = torch.from_numpy(np.stack(columns, 1).astype(np.int64)).to(device)
    out = pool(tensor)
    assert out.dtype == torch.int64 and out.device.type == device.type and out.shape[1] == 4
    np.testing.assert_array_equal(out.cpu().numpy(), np.stack(
        [expected["x"], expected["y"], expected["t"], expected["p"]], 1).astype(np.int64))
    events = Events.from_columns(*columns, device=device)
    out = pool(events)
    assert isinstance(out, Events) and out.t.dtype == torch.int64
    assert out.t.device.type == device.type
    assert out.t.cpu().tolist() == expected["t"].tolist()


@pytest.mark.parametrize("kind", ["numpy", "tensor", "events"])
def test_empty_input_gives_empty_output_of_same_kind(kind):
    pool = LIFPooling((8, 8, 2), 2)
    arr = np.empty(0, dtype=DVS_DTYPE)
    data = {
        "numpy": arr,
        "tensor": torch.empty(0, 4, dtype=torch.float64),
        "events": Events.empty(),
    }[kind]
    out = pool(data)
    assert type(out) is type(data) and len(out[0] if kind == "events" else out) == 0
    if kind == "numpy":
        assert out.dtype == arr.dtype
    if kind == "tensor":
        assert out.shape == (0, 4) and out.dtype == torch.float64


def test_single_event_gives_at_most_one_spike(lif_path):
    arr = np.array([(5, 5, True, 1_000)], dtype=DVS_DTYPE)
    assert LIFPooling((8, 8, 2), 4, weight=0.5)(arr).tolist() == []
    # it fires in step 0, whose end is clipped to t_end = the event's own time
    assert LIFPooling((8, 8, 2), 4, weight=1.5)(arr).tolist() == [(1, 1, True, 1_000)]
    assert lif_path is None or lif_path  # the closed form was tried


def test_int64_timestamps_at_large_magnitude_and_shift_invariance(rng):
    sensor = (12, 12, 2)
    arr = bursty_stream(rng, 20, sensor, gap_max=5000, burst=100)
    pool = LIFPooling(sensor, 3, dt=13, tau=90.0, weight=0.45)
    out = pool(arr)
    assert len(out) > 10
    assert_shift_equivariant(pool, arr, out, (1_700_000_000_000_000, 1_700_000_000_000_001 + 10**9))
    # output times are exact: t_start + (k + 1) * dt, or t_end
    t0, t1 = arr["t"].min() + 1_700_000_000_000_000, arr["t"].max() + 1_700_000_000_000_000
    shifted = arr.copy()
    shifted["t"] += 1_700_000_000_000_000
    t = pool(shifted)["t"]
    assert np.all(((t - t0) % 13 == 0) | (t == t1))


def test_flipping_polarity_flips_the_output(rng):
    arr = bursty_stream(rng, 15, (12, 10, 2), gap_max=400, burst=80)
    pool = LIFPooling((12, 10, 2), (3, 2), dt=9, tau=60.0, weight=0.5, mutual_inhibition=0.2)
    flipped = arr.copy()
    flipped["p"] = ~flipped["p"]
    expected = [(x, y, t, not p) for x, y, t, p in as_tuples(pool(arr))]
    assert len(expected) > 0 and as_tuples(pool(flipped)) == sorted(expected)


@settings(max_examples=30, deadline=None)
@given(beta=st.sampled_from([0.0, 0.5, 0.8, 1.0]), **LIF_CASES)
def test_property_matches_module(**case):
    arr, pool = lif_case(**case)
    assert as_tuples(pool(arr)) == lif_dense_reference(arr, pool)


def test_float_timestamps_and_fractional_dt(lif_path):
    # float64 times: t_start + (k + 1) * dt exactly as floats
    arr = np.array([(0, 0, True, 0.25), (1, 0, True, 0.5), (0, 1, True, 2.0)],
                   dtype=[("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<f8")])
    out = LIFPooling((2, 2, 2), 2, dt=0.75, tau=math.inf, weight=0.6)(arr)
    assert out.tolist() == [(0, 0, True, 1.0)]  # 1.2 > 1 in step 0 (ends at 1.0)
    # integer times with a fractional dt: step ends rounded half up, 10 + 2.5 -> 13
    ints = np.array([(0, 0, True, 10), (1, 1, True, 11), (0, 0, True, 20)], dtype=DVS_DTYPE)
    out = LIFPooling((2, 2, 2), 2, dt=2.5, tau=math.inf, weight=0.6)(ints)
    assert out.tolist() == [(0, 0, True, 13)]
    assert lif_path is None or lif_path  # the closed form was tried


def test_long_sparse_recording_does_not_allocate_per_step(lif_path):
    # 10^12 steps of 1 us between the bursts: only the 3 active steps are ever computed.
    t = [0, 0, 0, 10**12, 10**12, 2 * 10**12]
    arr = np.array([(0, 0, True, ti) for ti in t], dtype=DVS_DTYPE)
    # weight 0.5: U = 1.5 fires at step 0, then 0.5 stays (no leak) or decays to 0 (leak).
    out = LIFPooling((4, 4, 2), 2, dt=1, tau=10.0, weight=0.5)(arr)
    assert out.tolist() == [(0, 0, True, 1)]  # 0 + 2 * 0.5 = 1 does not exceed 1
    out = LIFPooling((4, 4, 2), 2, dt=1, tau=math.inf, weight=0.5)(arr)
    assert out.tolist() == [(0, 0, True, 1), (0, 0, True, 10**12 + 1)]  # 0.5 + 1.0 > 1
    assert lif_path is None or lif_path  # the closed form was tried


def test_nmnist_matches_tonic_toframe_and_composes(nmnist):
    import tonic

    sensor = tonic.datasets.NMNIST.sensor_size
    pool = LIFPooling(sensor, 4, dt=1000, tau=10_000.0, weight=0.3)
    out = pool(nmnist)
    assert len(out) > 100 and out.dtype == nmnist.dtype
    # Oracle: Tonic's own binning (windows [t0 + k dt, t0 + (k + 1) dt)), then the module.
    duration = int(nmnist["t"].max() - nmnist["t"].min())
    assert duration % 1000  # Tonic drops events on the last window edge otherwise
    frames = tonic.transforms.ToFrame(sensor, time_window=1000, include_incomplete=True)(nmnist)
    spikes, _ = SpikingPooling.from_transform(pool)(torch.from_numpy(frames).float()[:, None])
    step, _, p, y, x = (c.numpy() for c in spikes.nonzero(as_tuple=True))
    np.testing.assert_array_equal(np.bincount(step, minlength=len(frames)),
                                  np.bincount((out["t"] - nmnist["t"].min() - 1) // 1000,
                                              minlength=len(frames)))
    assert as_tuples(out) == sorted(zip(x.tolist(), y.tolist(), np.minimum(
        nmnist["t"].min() + (step + 1) * 1000, nmnist["t"].max()).tolist(),
        (p > 0).tolist(), strict=True))
    # Round trip through Compose with ToFrame on the output sensor.
    assert (out["t"].max() - out["t"].min()) % 50_000  # as above
    frame = tonic.transforms.ToFrame(
        sensor_size=pool.output_sensor_size, time_window=50_000, include_incomplete=True
    )
    frames = tonic.transforms.Compose([pool, frame])(nmnist)
    assert frames.shape == (6, 2, 9, 9) and frames.sum() == len(out)


def test_defaults_keep_busy_blocks_and_drop_noise(rng):
    # 128x128, factor 4, dt = 1 ms: a busy 8x8-pixel patch (4 blocks, ~5 events/ms each) and
    # sparse uniform noise (~0.02 events/ms per block). The defaults keep the patch, drop noise.
    n_signal, n_noise = 20_000, 2_000
    sig = np.zeros(n_signal, dtype=DVS_DTYPE)
    sig["x"], sig["y"] = rng.integers(60, 68, (2, n_signal))
    sig["p"], sig["t"] = rng.random(n_signal) < 0.5, rng.integers(0, 1_000_000, n_signal)
    noise = random_stream(rng, n_noise, (128, 128, 2), t_max=1_000_000)
    arr = np.sort(np.concatenate([sig, noise]), order="t", kind="stable")
    out = LIFPooling((128, 128, 2), 4)(arr)
    in_patch = (out["x"] >= 15) & (out["x"] < 17) & (out["y"] >= 15) & (out["y"] < 17)
    assert in_patch.sum() > 0.05 * n_signal
    assert (~in_patch).sum() < 0.01 * n_noise


def test_calibrate_weight_hits_target(rng):
    sensor = (32, 32, 2)
    arr = bursty_stream(rng, 200, sensor, gap_max=2000, burst=300)
    for ratio in (0.05, 0.2):
        weight = calibrate_weight(
            arr, sensor, 4, target_ratio=ratio, dt=100, tau=1000.0, rtol=0.01
        )
        got = len(LIFPooling(sensor, 4, dt=100, tau=1000.0, weight=weight)(arr)) / len(arr)
        assert got == pytest.approx(ratio, rel=0.05)
    seconds = (arr["t"].max() - arr["t"].min()) * 1e-6
    weight = calibrate_weight(arr, sensor, 4, target_rate=50_000.0, rtol=0.01)
    assert len(LIFPooling(sensor, 4, weight=weight)(arr)) / seconds == pytest.approx(
        50_000.0, rel=0.05)


def test_calibrate_weight_errors():
    arr = np.array([(0, 0, True, 0), (1, 1, True, 5)], dtype=DVS_DTYPE)
    with pytest.raises(ValueError, match="exactly one of target_ratio and target_rate"):
        calibrate_weight(arr, (4, 4, 2), 2)
    with pytest.raises(ValueError, match="exactly one"):
        calibrate_weight(arr, (4, 4, 2), 2, target_ratio=0.1, target_rate=10.0)
    with pytest.raises(ValueError, match="non-empty"):
        calibrate_weight(arr[:0], (4, 4, 2), 2, target_ratio=0.1)
    with pytest.raises(ValueError, match="target_ratio must be a positive"):
        calibrate_weight(arr, (4, 4, 2), 2, target_ratio=-1.0)
    with pytest.raises(ValueError, match="reaches the target"):
        calibrate_weight(arr, (4, 4, 2), 2, target_ratio=100.0, max_evaluations=5)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"dt": 0}, ValueError, "dt must be a positive"),
        ({"dt": float("inf")}, ValueError, "dt must be a positive"),
        ({"tau": -1.0}, ValueError, "tau must be a positive number"),
        ({"tau": "1"}, TypeError, "tau must be a positive number"),
        ({"threshold": 0.0}, ValueError, "threshold must be a positive"),
        ({"weight": float("nan")}, ValueError, "weight must be a positive"),
        ({"mutual_inhibition": -1}, ValueError, "mutual_inhibition must be a non-negative"),
        ({"reset_mechanism": "soft"}, ValueError, "reset_mechanism must be one of"),
        ({"reset_mechanism": None}, TypeError, "reset_mechanism must be one of"),
        ({"factor": 9}, ValueError, "larger than the sensor"),
    ],
)
def test_bad_settings_raise(kwargs, error, message):
    with pytest.raises(error, match=message):
        LIFPooling((8, 8, 2), **kwargs)


def test_transform_is_frozen_and_exposes_beta():
    pool = LIFPooling((8, 8, 2), 2, dt=1000, tau=10_000)
    assert pool.beta == pytest.approx(math.exp(-0.1))
    with pytest.raises(dataclasses.FrozenInstanceError):
        pool.weight = 1.0


@pytest.mark.parametrize("reset", ["subtract", "zero", "none"])
@pytest.mark.parametrize("inhibition", [0.0, 0.4])
@pytest.mark.parametrize("tau", [math.inf, 25.0])
@pytest.mark.parametrize("density", ["sparse", "dense"])
def test_event_driven_equals_stepped_reference(reset, inhibition, tau, density):
    # The kernel visits only the (region, step) cells that hold events and jumps over the
    # rest in closed form; the oracle steps the module through every step of dense frames.
    rng = np.random.default_rng(7)
    sensor = (12, 10, 2)
    if density == "sparse":  # most steps and most regions empty, long silences
        arr = random_stream(rng, 300, sensor, t_max=6_000)
    else:  # several events per region in most steps
        arr = random_stream(rng, 4000, sensor, t_max=600)
    pool = LIFPooling(sensor, 2, dt=3, tau=tau, weight=0.45 if density == "dense" else 1.3,
                      mutual_inhibition=inhibition, reset_mechanism=reset)
    out = as_tuples(pool(arr))
    assert len(out) > 20
    assert out == lif_dense_reference(arr, pool)


@pytest.mark.parametrize("reset", ["subtract", "none"])
@pytest.mark.parametrize("tau", [math.inf, 33.0, 1000.0])
def test_long_firing_chains_equal_stepping(reset, tau, lif_path):
    # A burst drives the membrane far above threshold; the neuron then fires through the
    # silence for more steps than are stepped one by one before the closed form takes over.
    burst = [(x, y, True, t) for t in range(2) for x in range(2) for y in range(2)]
    late = [(0, 0, True, 1500), (1, 1, False, 1510), (0, 0, True, 4000)]
    arr = np.array(burst + late, dtype=DVS_DTYPE)
    pool = LIFPooling((4, 4, 2), 2, dt=1, tau=tau, weight=3.1, reset_mechanism=reset)
    out = as_tuples(pool(arr))
    assert len(out) > 20
    assert out == lif_dense_reference(arr, pool)
    assert lif_path is None or lif_path  # the closed form was tried


def test_huge_dt_puts_everything_in_one_step(lif_path):
    # dt beyond int64 (1e20 us): no OverflowError; all events in step 0, which ends after
    # t_end, so its spikes are clipped to t_end.
    arr = np.array([(0, 0, True, 0), (1, 1, True, 5), (3, 3, False, 7)], dtype=DVS_DTYPE)
    for dt in (1e20, 9.3e18, float(2**63), 8.0):
        out = LIFPooling((4, 4, 2), 2, dt=dt, tau=math.inf, weight=0.6)(arr)
        assert out.tolist() == [(0, 0, True, 7)]
    floats = arr.astype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<f8")])
    out = LIFPooling((4, 4, 2), 2, dt=1e300, tau=math.inf, weight=0.6)(floats)
    assert out.tolist() == [(0, 0, True, 7.0)]
    assert lif_path is None or lif_path  # the closed form was tried


@pytest.mark.parametrize("t_dtype", ["<i8", "<f8"])
def test_tiny_dt_whose_step_count_overflows_int64_is_refused(t_dtype, lif_path):
    arr = np.array([(0, 0, True, 0), (0, 0, True, 3), (0, 0, True, 9)],
                   dtype=[("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", t_dtype)])
    with pytest.raises(ValueError, match=r"dt = 1e-30 .* more than the 2\*\*62"):
        LIFPooling((4, 4, 2), 2, dt=1e-30, weight=1.5)(arr)
    # the largest representable step counts still work
    assert len(LIFPooling((4, 4, 2), 2, dt=1e-17, weight=1.5)(arr)) == 3


def test_stream_span_beyond_int64_step_arithmetic_is_refused():
    arr = np.array([(0, 0, True, -(2**62)), (0, 0, True, 2**62)], dtype=DVS_DTYPE)
    with pytest.raises(ValueError, match=r"spans .* more than 2\*\*62"):
        LIFPooling((4, 4, 2), 2, dt=1e18, weight=1.5)(arr)


def test_firing_through_a_long_gap_is_closed_form(lif_path):
    # No leak, threshold 2**-20, one event of weight 1: the membrane 1 - j * 2**-20 stays above
    # threshold for 2**20 - 2 silent steps (exact float32 values), one spike per step; a
    # stepping kernel loops a million times here.
    arr = np.array([(0, 0, True, 0), (0, 0, True, 2**21)], dtype=DVS_DTYPE)
    pool = LIFPooling((4, 4, 2), 2, dt=1, tau=math.inf, threshold=2.0**-20, weight=1.0)
    out = pool(arr)
    assert len(out) == 2**20
    np.testing.assert_array_equal(out["t"][:-1], np.arange(1, 2**20))
    assert out["t"][-1] == 2**21 and np.all(out["p"]) and not np.any(out["x"] | out["y"])
    assert lif_path is None or lif_path  # the closed form was tried


def test_output_beyond_the_bound_is_refused_with_its_count(lif_path):
    # reset "none", no leak: a neuron above threshold fires at every one of 10**12 steps.
    arr = np.array([(0, 0, True, 0), (0, 0, True, 10**12)], dtype=DVS_DTYPE)
    pool = LIFPooling((4, 4, 2), 2, dt=1, tau=math.inf, weight=1.5, reset_mechanism="none")
    # Two of the spikes are at the cells (steps 0 and 10**12), the rest fired through silence.
    with pytest.raises(ValueError, match=r"at least 1,000,000,000,001 events \(999,999,999,999 "
                       r"of them fired by LIF neurons .* limit of 100,000,000; a lower weight "
                       r".*max_output_events\(n\)"):
        pool(arr)
    short = np.array([(0, 0, True, 0), (0, 0, True, 99)], dtype=DVS_DTYPE)
    assert len(pool(short)) == 100
    with max_output_events(99), pytest.raises(ValueError, match="at least 100 events"):
        pool(short)
    with max_output_events(None):
        assert len(pool(short)) == 100
    assert lif_path is None or lif_path  # the closed form was tried
