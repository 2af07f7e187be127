"""LIF pooling's closed form (small calls) against the rounds and the stepped module."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evdown_torch import LIFPooling
from evdown_torch.transforms.functional import lif as lif_kernel
from evdown_torch.transforms.functional import lif_closed_form
from tests.helpers import DVS_DTYPE, random_stream
from tests.transforms import test_lif
from tests.transforms.test_lif import SETTINGS, bursty_stream, dense_reference, tuples


@pytest.fixture
def answers(monkeypatch) -> list[bool]:
    """The closed form tried on every call (not only those of ``MIN_ROUNDS`` rounds or more);
    the list records, per call, whether it answered (``False``: left to the rounds)."""
    calls: list[bool] = []

    def recording(*args, **kwargs):
        out = lif_closed_form.certain_spikes(*args, **kwargs)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(lif_kernel, "MIN_ROUNDS", 1)
    monkeypatch.setattr(lif_kernel, "certain_spikes", recording)
    return calls


def by_rounds(pool: LIFPooling, arr: np.ndarray, monkeypatch) -> np.ndarray:
    """The transform's output with the closed form switched off (the rounds only)."""
    with monkeypatch.context() as patch:
        patch.setattr(lif_kernel, "certain_spikes", lambda *args, **kwargs: None)
        return pool(arr)


@pytest.mark.parametrize("which", range(len(SETTINGS)))
@pytest.mark.parametrize("kind", ["bursty", "dense", "sparse"])
def test_closed_form_gives_the_rounds_spikes(which, kind, answers, monkeypatch):
    rng = np.random.default_rng(100 + which)
    sensor = (10, 8, 2)
    for _ in range(4):
        if kind == "bursty":  # long silences: decay over gaps, firing chains into them
            arr = bursty_stream(rng, 8, sensor, gap_max=150, burst=60)
        elif kind == "dense":  # several events per region in most steps: long rows
            arr = random_stream(rng, 1500, sensor, t_max=400)
        else:
            arr = random_stream(rng, 200, sensor, t_max=5000)
        pool = LIFPooling(sensor, (2, 3), dt=4, **SETTINGS[which])
        np.testing.assert_array_equal(pool(arr), by_rounds(pool, arr, monkeypatch))
    assert len(answers) == 4
    if SETTINGS[which]["tau"] == 1e-3:  # beta = 0 has nothing to integrate: left to the rounds
        assert not any(answers)
    elif SETTINGS[which]["tau"] != math.inf:  # (without leak, membranes exactly on the
        assert any(answers)  # threshold are common: weight 0.25, say)


def test_closed_form_answers_the_default_settings_on_nmnist(nmnist, answers, monkeypatch):
    for factor in (2, 4):
        pool = LIFPooling((34, 34, 2), factor)
        answers.clear()
        out = pool(nmnist)
        assert answers == [True] and len(out) > 500
        np.testing.assert_array_equal(out, by_rounds(pool, nmnist, monkeypatch))


@pytest.mark.parametrize("block", [2, 3, 8, 16])
def test_greedy_block_length_does_not_change_the_spikes(block, nmnist, answers, monkeypatch):
    # Passes between look-backs: 2 looks back after every other pass; longer blocks waste the
    # passes after a neuron still above threshold and must undo them.
    monkeypatch.setattr(lif_closed_form, "_BLOCK", block)
    rng = np.random.default_rng(7)
    dense = random_stream(rng, 1500, (10, 8, 2), t_max=400)
    for pool, arr in ((LIFPooling((34, 34, 2), 4), nmnist),
                      (LIFPooling((10, 8, 2), (2, 3), dt=4, **SETTINGS[2]), dense)):
        answers.clear()
        out = pool(arr)
        assert answers == [True]
        np.testing.assert_array_equal(out, by_rounds(pool, arr, monkeypatch))


def test_a_decision_within_float32_rounding_is_left_to_the_rounds(answers):
    # No leak, weight 0.1: after ten ON events the float32 membrane is 1.0000001 > 1 (the
    # kernel and the module fire) while the exact sum of the ten float32 weights exceeds the
    # threshold by only 1.5e-8, less than the rounding bound: the rounds decide.
    arr = np.array([(0, 0, True, 10 * k) for k in range(12)], dtype=DVS_DTYPE)
    pool = LIFPooling((2, 2, 2), 2, dt=10, tau=math.inf, weight=0.1)
    out = pool(arr)
    assert answers == [False]
    assert tuples(out) == dense_reference(arr, pool) == [(0, 0, 100, True)]


def test_close_but_certain_decisions_are_answered(answers):
    # weight 0.45, no leak: after k events the membrane is 0.45 k minus the spikes so far, at
    # least 0.05 from the threshold for k <= 12; float32 rounding is far smaller.
    arr = np.array([(k % 2, 0, True, 10 * k) for k in range(12)], dtype=DVS_DTYPE)
    pool = LIFPooling((2, 2, 2), 2, dt=10, tau=math.inf, weight=0.45)
    out = tuples(pool(arr))
    assert answers == [True]
    assert out == dense_reference(arr, pool) and len(out) == 5


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    events=st.lists(
        st.tuples(st.integers(0, 6), st.integers(0, 4), st.integers(0, 400), st.booleans()),
        min_size=1,
        max_size=80,
    ),
    dt=st.integers(1, 50),
    beta=st.sampled_from([0.5, 0.8, 0.95, 1.0]),
    weight=st.sampled_from([0.3, 0.5, 1.0, 2.5]),
    inhibition=st.sampled_from([0.0, 0.25, 0.5]),
    reset=st.sampled_from(["subtract", "zero", "none"]),
    factor=st.sampled_from([1, 2, 3, (2, 5)]),
)
def test_property_closed_form_matches_module(events, dt, beta, weight, inhibition, reset, factor):
    arr = np.array([(x, y, p, t) for x, y, t, p in events], dtype=DVS_DTYPE)
    tau = math.inf if beta == 1.0 else -dt / math.log(beta)
    pool = LIFPooling((7, 5, 2), factor, dt=dt, tau=tau, weight=weight,
                      mutual_inhibition=inhibition, reset_mechanism=reset)
    with pytest.MonkeyPatch.context() as patch:  # the closed form on every call
        patch.setattr(lif_kernel, "MIN_ROUNDS", 1)
        assert tuples(pool(arr)) == dense_reference(arr, pool)


def test_batch_equals_one_by_one_through_the_closed_form(answers):
    rng = np.random.default_rng(5)
    sensor = (12, 10, 2)
    recordings = [random_stream(rng, n, sensor, t_max=3000) for n in (900, 1, 0, 400, 1200)]
    recordings.append(bursty_stream(rng, 6, sensor, gap_max=300, burst=80))
    recordings[3]["t"] += 10**9  # another clock
    pool = LIFPooling(sensor, 3, dt=20, tau=150.0, weight=0.45)
    expected = [pool(r) for r in recordings]
    answers.clear()
    got = pool.batch(recordings)
    assert answers == [True]
    assert sum(len(e) for e in expected) > 50
    for out, one in zip(got, expected, strict=True):
        np.testing.assert_array_equal(out, one)


@pytest.mark.parametrize(
    "case",
    [
        test_lif.test_huge_dt_puts_everything_in_one_step,
        test_lif.test_long_sparse_recording_does_not_allocate_per_step,
        test_lif.test_firing_through_a_long_gap_is_closed_form,
        test_lif.test_output_beyond_the_bound_is_refused_with_its_count,
        test_lif.test_integrate_and_fire_limit_on_events,
        test_lif.test_float_timestamps_and_fractional_dt,
        test_lif.test_single_event_gives_at_most_one_spike,
    ],
)
def test_edge_cases_through_the_closed_form(case, answers):
    case()
    assert answers  # the closed form was tried


@pytest.mark.parametrize("t_dtype", ["<i8", "<f8"])
def test_tiny_dt_refused_through_the_closed_form(t_dtype, answers):
    test_lif.test_tiny_dt_whose_step_count_overflows_int64_is_refused(t_dtype)


@pytest.mark.parametrize("reset", ["subtract", "zero", "none"])
@pytest.mark.parametrize("tau", [math.inf, 20.0, 10.0 / math.log(2)])
def test_empty_steps_through_the_closed_form(reset, tau, answers):
    test_lif.test_skipping_empty_steps_equals_stepping_through_them(reset, tau)
    assert answers


@pytest.mark.parametrize("reset", ["subtract", "none"])
@pytest.mark.parametrize("tau", [math.inf, 33.0, 1000.0])
def test_long_chains_through_the_closed_form(reset, tau, answers):
    test_lif.test_long_firing_chains_equal_stepping(reset, tau)
    assert answers
