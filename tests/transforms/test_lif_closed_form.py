"""LIF pooling's closed form (small calls) against the rounds and the stepped module."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from evdown_torch import Events, LIFPooling
from evdown_torch.transforms.functional.lif import closed_form as lif_closed_form
from evdown_torch.transforms.functional.lif import pooling as lif_kernel
from evdown_torch.transforms.functional.lif.chains import Leak
from tests import helpers


@pytest.fixture
def answers(lif_closed_form_answers) -> list[bool]:
    """The closed form tried on every call (see ``tests/conftest.py``)."""
    return lif_closed_form_answers


def by_rounds(pool: LIFPooling, arr: np.ndarray, monkeypatch) -> np.ndarray:
    """The transform's output with the closed form switched off (the rounds only)."""
    with monkeypatch.context() as patch:
        patch.setattr(lif_kernel, "certain_spikes", lambda *args, **kwargs: None)
        return pool(arr)


@pytest.mark.parametrize("which", range(len(helpers.LIF_SETTINGS)))
@pytest.mark.parametrize("kind", ["bursty", "dense", "sparse"])
def test_closed_form_gives_the_rounds_spikes(which, kind, answers, monkeypatch):
    rng = np.random.default_rng(100 + which)
    sensor = (10, 8, 2)
    for _ in range(4):
        if kind == "bursty":  # long silences: decay over gaps, firing chains into them
            arr = helpers.bursty_stream(rng, 8, sensor, gap_max=150, burst=60)
        elif kind == "dense":  # several events per region in most steps: long rows
            arr = helpers.random_stream(rng, 1500, sensor, t_max=400)
        else:
            arr = helpers.random_stream(rng, 200, sensor, t_max=5000)
        pool = LIFPooling(sensor, (2, 3), dt=4, **helpers.LIF_SETTINGS[which])
        np.testing.assert_array_equal(pool(arr), by_rounds(pool, arr, monkeypatch))
    assert len(answers) == 4
    tau = helpers.LIF_SETTINGS[which]["tau"]
    if tau == 1e-3:  # beta = 0 has nothing to integrate: left to the rounds
        assert not any(answers)
    elif tau != math.inf:  # (without leak, membranes exactly on the threshold are common:
        assert any(answers)  # weight 0.25, say)


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
    dense = helpers.random_stream(rng, 1500, (10, 8, 2), t_max=400)
    for pool, arr in ((LIFPooling((34, 34, 2), 4), nmnist),
                      (LIFPooling((10, 8, 2), (2, 3), dt=4, **helpers.LIF_SETTINGS[2]), dense)):
        answers.clear()
        out = pool(arr)
        assert answers == [True]
        np.testing.assert_array_equal(out, by_rounds(pool, arr, monkeypatch))


def test_a_decision_within_float32_rounding_is_left_to_the_rounds(answers):
    # No leak, weight 0.1: after ten ON events the float32 membrane is 1.0000001 > 1 (the
    # kernel and the module fire) while the exact sum of the ten float32 weights exceeds the
    # threshold by only 1.5e-8, less than the rounding bound: the rounds decide.
    arr = np.array([(0, 0, True, 10 * k) for k in range(12)], dtype=helpers.DVS_DTYPE)
    pool = LIFPooling((2, 2, 2), 2, dt=10, tau=math.inf, weight=0.1)
    out = pool(arr)
    assert answers == [False]
    assert helpers.as_tuples(out) == helpers.lif_dense_reference(arr, pool) == [(0, 0, 100, True)]


def test_close_but_certain_decisions_are_answered(answers):
    # weight 0.45, no leak: after k events the membrane is 0.45 k minus the spikes so far, at
    # least 0.05 from the threshold for k <= 12; float32 rounding is far smaller.
    arr = np.array([(k % 2, 0, True, 10 * k) for k in range(12)], dtype=helpers.DVS_DTYPE)
    pool = LIFPooling((2, 2, 2), 2, dt=10, tau=math.inf, weight=0.45)
    out = helpers.as_tuples(pool(arr))
    assert answers == [True]
    assert out == helpers.lif_dense_reference(arr, pool) and len(out) == 5


@settings(max_examples=60, deadline=None, derandomize=True)
@given(beta=st.sampled_from([0.5, 0.8, 0.95, 1.0]), **helpers.LIF_CASES)
def test_property_closed_form_matches_module(**case):
    arr, pool = helpers.lif_case(**case)
    with pytest.MonkeyPatch.context() as patch:  # the closed form on every call
        patch.setattr(lif_kernel, "MIN_ROUNDS", 1)
        assert helpers.as_tuples(pool(arr)) == helpers.lif_dense_reference(arr, pool)


def test_batch_equals_one_by_one_through_the_closed_form(answers):
    rng = np.random.default_rng(5)
    sensor = (12, 10, 2)
    recordings = [helpers.random_stream(rng, n, sensor, t_max=3000) for n in (900, 1, 0, 400, 1200)]
    recordings.append(helpers.bursty_stream(rng, 6, sensor, gap_max=300, burst=80))
    recordings[3]["t"] += 10**9  # another clock
    pool = LIFPooling(sensor, 3, dt=20, tau=150.0, weight=0.45)
    expected = [pool(r) for r in recordings]
    answers.clear()
    got = pool.batch(recordings)
    assert answers == [True]
    assert sum(len(e) for e in expected) > 50
    for out, one in zip(got, expected, strict=True):
        np.testing.assert_array_equal(out, one)


def _greedy_tables(rng: np.random.Generator, rows: int, width: int, beta: float, theta: float):
    """Random (2, R, width) tables as certain_spikes builds them: rows of random lengths,
    random empty steps between cells (0 to 4, some long), currents of 0 to 9 events of 0.3."""
    lengths = rng.integers(1, width + 1, rows)
    lengths[0] = width
    lam = -math.log(beta)
    scale = torch.ones(rows, width, dtype=torch.float64)
    between = torch.zeros(rows, width, dtype=torch.int64)
    inputs = torch.zeros(2, rows, width, dtype=torch.float64)
    for r, n in enumerate(lengths.tolist()):
        gaps = rng.choice([0, 0, 1, 2, 4, 9], n)
        steps = np.concatenate([[0], np.cumsum(gaps[:-1] + 1)])
        scale[r, :n] = torch.from_numpy(np.exp(lam * steps))
        between[r, : n - 1] = torch.from_numpy(gaps[:-1])
        counts = rng.integers(0, 10, (2, n)) * (rng.random((2, n)) < 0.7)
        inputs[:, r, :n] = torch.from_numpy(np.float32(0.3) * counts.astype(np.float32)
                                            ).double() * scale[r, :n]
    invalid = torch.arange(width) >= torch.from_numpy(lengths)[:, None]
    return torch.cumsum(inputs, -1), scale * theta, invalid, scale, between, lengths


def _greedy_reference(summed, level, scale, between, lengths, beta, theta, reset):
    """Slow oracle: the recurrence neuron by neuron, cell by cell, in float64 (firing at a
    cell where the scaled membrane exceeds the scaled threshold; reset "subtract": a firing
    still above threshold fires on through the empty steps after it, stepped one by one)."""
    fired = torch.zeros(summed.shape, dtype=torch.bool)
    chains = torch.zeros(summed.shape, dtype=torch.int64)
    still_above = 0  # firings after which the search must look back
    for p in range(summed.shape[0]):
        for r, n in enumerate(lengths.tolist()):
            debt = 0.0
            for c in range(n):
                s, lev, sc = summed[p, r, c].item(), level[r, c].item(), scale[r, c].item()
                if s - lev <= debt:
                    continue
                fired[p, r, c] = True
                if reset == "zero":
                    debt = s
                    continue
                u, m, v = (s - debt) / sc, 0, (s - debt) / sc
                while m < between[r, c].item():
                    v = beta * v - theta
                    if v <= theta:
                        break
                    m += 1
                chains[p, r, c] = m
                still_above += s - lev > debt + lev / beta
                debt += lev / beta * sum(beta**-t for t in range(m + 1))
                assert u > theta
    return fired, chains, still_above


@pytest.mark.parametrize("reset", ["subtract", "zero"])
@pytest.mark.parametrize("seed", range(4))
def test_greedy_search_matches_a_sequential_reference(reset, seed, monkeypatch):
    # Heavy inputs (up to 2.7 per cell against a threshold of 1): many neurons still above
    # threshold after a firing (look-backs) and chains through the empty steps (subtract).
    monkeypatch.setattr(lif_closed_form, "_BLOCK", [16, 5, 3, 16][seed])
    rng = np.random.default_rng(seed)
    beta, theta = 0.9, 1.0
    summed, level, invalid, scale, between, lengths = _greedy_tables(rng, 9, 40, beta, theta)
    leak = Leak(torch.tensor(beta, dtype=torch.float32), torch.tensor(theta), reset)
    gain = level * (1.0 / beta) if reset == "subtract" else None
    fired, chains = lif_closed_form._greedy_firings(
        summed, level, gain, invalid, scale, between if reset == "subtract" else None,
        leak=leak,
    )
    want_fired, want_chains, still_above = _greedy_reference(
        summed, level, scale, between, lengths, leak.beta, theta, reset)
    assert torch.equal(fired, want_fired)
    assert int(want_fired.sum()) > 50
    if reset == "subtract":  # the case exercises look-backs and chains
        assert still_above > 2 and int((want_chains > 0).sum()) > 0
        assert torch.equal(chains if chains is not None else torch.zeros_like(want_chains),
                           want_chains)
    else:
        assert chains is None


@pytest.mark.parametrize("path", ["occupancy", "sort", "stable"])
def test_event_cells_paths_group_events_alike(path, monkeypatch):
    # The cells (region, step) with their (OFF, ON) counts, against a dictionary built
    # event by event; each of the three groupings (bool table of keys, sort of the keys,
    # stable sort of the regions where the key overflows int64).
    rng = np.random.default_rng(3)
    n, sensor = 3000, (12, 10, 2)  # factor (3, 2): 4 x 5 regions
    x, y = rng.integers(0, sensor[0], n), rng.integers(0, sensor[1], n)
    steps = np.sort(rng.integers(0, 700, n))
    p = rng.random(n) < 0.4
    events = Events.from_columns(x, y, steps, p)
    wo, ho = 4, 5
    top = int(steps.max())
    if path == "sort":
        monkeypatch.setattr(lif_kernel, "OCCUPANCY_KEYS_PER_EVENT", 0)
    elif path == "stable":
        top = (1 << 62) // (wo * ho) + 1
    region, step, current = lif_kernel._event_cells(
        events, torch.from_numpy(steps), fx=3, fy=2, wo=wo, plane=wo * ho, top_step=top,
        weight=0.5, mutual_inhibition=0.25,
    )
    counts: dict[tuple[int, int], list[int]] = {}
    for xi, yi, si, pi in zip(x.tolist(), y.tolist(), steps.tolist(), p.tolist(), strict=True):
        counts.setdefault(((yi // 2) * wo + xi // 3, si), [0, 0])[int(pi)] += 1
    keys = sorted(counts)
    assert list(zip(region.tolist(), step.tolist(), strict=True)) == keys
    want = [[0.5 * c[0] - 0.25 * c[1], 0.5 * c[1] - 0.25 * c[0]] for c in map(counts.get, keys)]
    assert current.tolist() == want
