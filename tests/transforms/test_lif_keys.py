"""LIF pooling's cheap paths for live chunks: counted cells and searched steps, exactly."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch import Events, LIFPooling
from evdown_torch.transforms.functional.lif import keys
from evdown_torch.transforms.functional.lif import pooling as lif_kernel
from evdown_torch.transforms.functional.lif import steps as lif_steps
from tests.helpers import LIF_SETTINGS, as_tuples, lif_dense_reference, random_stream


@pytest.mark.parametrize(("batch", "first_step"), [(1, 40), (3, 40), (1, 2**40)])
def test_counted_cells_equal_grouped_cells(batch, first_step, monkeypatch):
    # Many events on few keys: counting every key gives the cells and currents of the
    # grouping paths, also for recordings stacked vertically (a batch's plane) and for
    # steps beyond int32 (an old stream's).
    rng = np.random.default_rng(5)
    n, wo, ho = 20_000, 4, 5  # factor (3, 2) on 12 x 10 pixels per recording
    x, y = rng.integers(0, 12, n), rng.integers(0, 10 * batch, n)
    steps = torch.from_numpy(np.sort(rng.integers(0, 50, n)) + first_step)
    events = Events.from_columns(x, y, steps, rng.random(n) < 0.3)
    kwargs = dict(fx=3, fy=2, wo=wo, plane=batch * wo * ho, top_step=first_step + 55, weight=0.5,
                  mutual_inhibition=0.25)
    counted = lif_kernel._event_cells(events, steps, **kwargs)
    monkeypatch.setattr(lif_kernel, "COUNTED_KEYS_PER_EVENT", 0)
    grouped = lif_kernel._event_cells(events, steps, **kwargs)
    for a, b in zip(counted, grouped, strict=True):
        assert a.dtype == b.dtype
        assert torch.equal(a, b)


def test_searched_steps_equal_division():
    # Steps found by searching the steps' first times are the floor division's, from any
    # t_start at or before the first event, whatever the span and dt.
    rng = np.random.default_rng(6)
    searched = 0
    for _ in range(60):
        n = int(rng.integers(1, 60_000))
        span = int(rng.choice([10, 1_000, 10**6, 10**9]))
        t = torch.from_numpy(np.sort(rng.integers(0, span, n)) + int(rng.integers(-10**12, 10**12)))
        t_start = t[0] - int(rng.integers(0, 5_000))
        dt = float(rng.choice([1, 3, 997, 1_000, 10**5]))
        steps, last, used_dt = lif_steps.step_indices(t, dt, t_start=t_start)
        want = torch.div(t - t_start, int(used_dt), rounding_mode="floor")
        assert torch.equal(steps, want)
        assert last == int(want[-1])
        searched += lif_steps._searchable(t, used_dt) and lif_steps._step_runs(
            t, int(t_start), int(used_dt)) is not None
    assert searched > 5


@pytest.mark.parametrize("settings", LIF_SETTINGS[:4])
def test_live_chunks_equal_the_dense_oracle(settings):
    # Chunks of 10 steps with about 20k events each on a small sensor (the counted cells and
    # searched steps of a live replay): the session's output is the dense module's.
    rng = np.random.default_rng(7)
    arr = random_stream(rng, 100_000, (12, 10, 2), t_max=50_000)
    pool = LIFPooling((12, 10, 2), 3, dt=1000, **settings)
    session = pool.session()
    cuts = np.searchsorted(arr["t"], np.arange(0, 50_001, 10_000))
    parts = [session(arr[a:b]) for a, b in zip(cuts, cuts[1:])] + [session.flush()]
    got = np.concatenate(parts)
    assert as_tuples(got) == lif_dense_reference(arr, pool)
    np.testing.assert_array_equal(got, pool(arr))


def test_spikes_ordered_by_table_as_by_sort(monkeypatch):
    # Distinct (step, neuron) spikes: the table of keys orders them as the sort does.
    rng = np.random.default_rng(8)
    neurons, low, top = 40, 1_000, 1_030
    key = torch.from_numpy(rng.permutation((top - low + 1) * neurons)[:600])
    spike_step, neuron = key // neurons + low, key % neurons
    by_table = keys.by_step_then_neuron(spike_step, neuron, neurons, low, top)
    monkeypatch.setattr(keys, "TABLE_KEYS_PER_SPIKE", 0)
    by_sort = keys.by_step_then_neuron(spike_step, neuron, neurons, low, top)
    for a, b in zip(by_table, by_sort, strict=True):
        assert torch.equal(a, b)
    assert bool((torch.diff(by_table[0] * neurons + by_table[1]) > 0).all())


@pytest.mark.parametrize("dt", [997, 1000, 2.5])
def test_large_chunks_cut_anywhere_equal_the_batch(dt):
    # Chunks of 20k to 40k events cut at random (within steps, a first chunk shorter than a
    # step, pending events that stay pending): the pieces a session counts give the batch.
    rng = np.random.default_rng(9)
    arr = random_stream(rng, 120_000, (12, 10, 2), t_max=30_000)
    pool = LIFPooling((12, 10, 2), (3, 2), dt=dt, tau=8_000.0, weight=0.05,
                      mutual_inhibition=0.02)
    session = pool.session()
    cuts = [0, 5, 20, 30_000, 30_001, 70_000, 100_000, 120_000]
    got = np.concatenate([session(arr[a:b]) for a, b in zip(cuts, cuts[1:])]
                         + [session.flush()])
    want = pool(arr)
    assert len(want) > 100
    np.testing.assert_array_equal(got, want)
    if float(dt).is_integer():
        assert as_tuples(want) == lif_dense_reference(arr, pool)
