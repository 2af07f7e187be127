"""LIFPooling's compiled loops (cells counted, membranes cell by cell) against the eager
kernel and the module on dense frames."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch

import evdown_torch
from evdown_torch import Events, LIFPooling, eager_kernels
from evdown_torch.transforms.functional.lif.pooling import lif_pooling
from evdown_torch.transforms.functional.lif.settings import LIFSettings
from tests.helpers import (
    FLOAT_DTYPE,
    LIF_SETTINGS,
    as_tuples,
    assert_batches_on_both_paths,
    assert_identical,
    assert_sessions_on_both_paths,
    both_paths,
    bursty_stream,
    lif_dense_reference,
    near_their_limits,
    random_stream,
    spy,
)

pytest.importorskip("numba")

SENSOR = (10, 7, 2)
FACTORS = [1, 2, (2, 3), (3, 1), (4, 3)]  # (3, 1), (4, 3): not dividing 10 x 7
ROUNDS = importlib.import_module("evdown_torch.transforms.functional.lif.rounds")
COMPILED = importlib.import_module("evdown_torch.transforms.functional.compiled.lif")
CELLS = importlib.import_module("evdown_torch.transforms.functional.compiled.lif_cells")


@pytest.mark.parametrize("factor", FACTORS)
@pytest.mark.parametrize("settings", LIF_SETTINGS)
def test_compiled_equals_eager_and_the_module(settings, factor, rng):
    arr = random_stream(rng, 900, SENSOR, t_max=600, sort=False)
    transform = LIFPooling(SENSOR, factor=factor, dt=4, **settings)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert sorted(as_tuples(compiled)) == lif_dense_reference(arr, transform)


@pytest.mark.parametrize("settings", LIF_SETTINGS)
def test_bursts_with_firing_chains_through_long_silences(settings, rng):
    arr = bursty_stream(rng, 40, SENSOR, gap_max=300)
    transform = LIFPooling(SENSOR, factor=(3, 2), dt=3, **settings)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert sorted(as_tuples(compiled)) == lif_dense_reference(arr, transform)


def test_the_compiled_rounds_run_and_the_eager_rounds_only_for_longer_chains(monkeypatch, rng):
    loops = spy(monkeypatch, COMPILED, "cells_until_chain")
    eager_rounds = spy(monkeypatch, ROUNDS, "_round")
    arr = random_stream(rng, 400, SENSOR, t_max=20)  # 10 steps: eager takes the rounds
    transform = LIFPooling(SENSOR, factor=2, dt=2, tau=8.0, weight=0.3)
    with eager_kernels(False):  # the compiled path, even where EVDOWN_EAGER=1
        transform(arr)
    assert len(loops) > 0 and len(eager_rounds) == 0
    with eager_kernels():
        transform(arr)
    assert len(eager_rounds) > 0
    # A neuron firing on through several empty steps: that round is the eager one's, and
    # the loop goes on after it.
    loops.clear()
    eager_rounds.clear()
    strong = LIFPooling(SENSOR, factor=2, dt=1, tau=40.0, weight=3.0)
    chain = np.zeros(8, dtype=arr.dtype)
    chain["t"] = [0, 0, 0, 0, 50, 51, 52, 200]
    chain["p"] = True
    chain["x"][-1] = 9  # another region: the stream ends at 200
    compiled, eager = both_paths(lambda: strong(chain))
    assert_identical(compiled, eager)
    assert len(loops) >= 2 and len(eager_rounds) >= 1
    assert sorted(as_tuples(compiled)) == lif_dense_reference(chain, strong)


@pytest.mark.parametrize(("weight", "gap", "loop_only"), [
    (0.7, 50, True),  # 2.8 fires, then 0.975 * 2.8 - 1 = 1.73 fires, 0.69: one chain spike
    (1.2, 50, True),  # 4.8, then 3.68, 2.59, 1.53 fire, 0.49: three chain spikes
    (0.7, 1100, False),  # decays over 2 ** 10 steps or more after its chain: the eager round
    (3.0, 50, False),  # fires on past EXACT_CHAIN_STEPS: the closed form's, the eager round
])
def test_short_firing_chains_stay_in_the_compiled_loop(monkeypatch, weight, gap, loop_only):
    loops = spy(monkeypatch, COMPILED, "cells_until_chain")
    eager_rounds = spy(monkeypatch, ROUNDS, "_round")
    strong = LIFPooling(SENSOR, factor=2, dt=1, tau=40.0, weight=weight)  # beta 0.9753
    chain = np.zeros(8, dtype=random_stream(np.random.default_rng(0), 1, SENSOR).dtype)
    chain["t"] = [0, 0, 0, 0, gap, gap + 1, gap + 2, gap + 150]
    chain["p"] = True
    chain["x"][-1] = 9  # another region: the stream ends after the last cell
    compiled, eager = both_paths(lambda: strong(chain))
    assert_identical(compiled, eager)
    assert sorted(as_tuples(compiled)) == lif_dense_reference(chain, strong)
    with eager_kernels(False):
        eager_rounds.clear()
        loops.clear()
        strong(chain)
    assert len(loops) >= 1
    assert (len(eager_rounds) == 0) == loop_only
    # the spike of the cell at t = 0 and those of its chain (above), each at its step's end
    in_gap = [t for t, x in zip(compiled["t"].tolist(), compiled["x"].tolist(), strict=True)
              if 0 < t <= gap and x == 0]
    spikes = {0.7: 2, 1.2: 4}.get(weight) if gap < 1000 else None
    if spikes is not None:
        assert len(in_gap) == spikes


def test_the_decays_are_the_eager_ones_wherever_a_cell_lies():
    """torch's float32 power rounds ``0.999 ** 168`` one unit apart in its vectorised loop and
    in its scalar tail, and the threshold lies between the two membranes: both paths read the
    same decays (lif/powers), so they give the same spikes in every region."""
    beta, gap, weight = 0.999, 168, 0.3
    b32 = torch.tensor(beta, dtype=torch.float32)
    membrane = torch.tensor(3.0, dtype=torch.float32) * torch.tensor(weight, dtype=torch.float32)
    current = torch.tensor(2.0, dtype=torch.float32) * torch.tensor(weight, dtype=torch.float32)
    decays = {float(torch.pow(b32, torch.full((64,), float(gap)))[0]),
              float(torch.pow(b32, torch.tensor([float(gap)]))[0])}
    # the threshold at the lower membrane: only the larger decay (if any) makes it fire
    threshold = min(float(b32 * (membrane * torch.tensor(d, dtype=torch.float32)) + current)
                    for d in decays)
    regions = 40
    x = [r for r in range(regions) for _ in range(5)]
    t = [0, 0, 0, gap + 1, gap + 1] * regions
    events = Events.from_columns(x, [0] * len(x), t, [1] * len(x))
    settings = LIFSettings(dt=1, beta=beta, threshold=threshold, weight=weight)
    compiled, eager = both_paths(lambda: lif_pooling(events, settings, sensor_size=(regions, 1, 2),
                                                     factor=(1, 1)))
    assert_identical(compiled, eager)


@pytest.mark.parametrize("dtype", [np.int64, np.float32, np.float64])
def test_timestamp_dtypes_near_their_limits(dtype, rng):
    arr = random_stream(rng, 800, SENSOR, t_max=200, sort=False)
    data = near_their_limits(arr, dtype, 200)  # int64 up to 2**63 - 11
    transform = LIFPooling(SENSOR, factor=(3, 2), dt=3 if dtype == np.int64 else 0.75,
                           tau=20.0, weight=0.4, mutual_inhibition=0.1)
    compiled, eager = both_paths(lambda: transform(data))
    assert_identical(compiled, eager)
    assert compiled.dtype == data.dtype and len(compiled) > 0
    if dtype == np.int64:
        assert int(compiled[:, 2].min()) >= 2**63 - 210


def test_float64_microseconds_of_a_wall_clock(rng):
    arr = random_stream(rng, 700, SENSOR, t_max=4000, dtype=FLOAT_DTYPE, sort=False)
    arr["t"] = arr["t"] * 0.1 + 1.7e15  # spaced by a few ulps of the clock
    transform = LIFPooling(SENSOR, factor=2, dt=2.5, tau=20.0, weight=0.5)
    compiled, eager = both_paths(lambda: transform(arr))
    assert_identical(compiled, eager)
    assert len(compiled) > 0


@pytest.mark.parametrize("settings", LIF_SETTINGS)
def test_sessions_in_odd_chunks_and_moving_between_paths(settings, rng):
    arr = bursty_stream(rng, 150, SENSOR, gap_max=200)[:1500]
    assert len(arr) == 1500  # every cut of ODD_CUTS falls inside the stream
    transform = LIFPooling(SENSOR, factor=(4, 3), dt=2.5, **settings)
    whole, _ = both_paths(lambda: transform(arr))
    assert_sessions_on_both_paths(transform, arr, whole)


def test_batches_sorted_stacked_and_with_empty_recordings(rng):
    transform = LIFPooling(SENSOR, factor=(3, 2), dt=3, tau=25.0, weight=0.6)

    def check(recording, out):
        expected = lif_dense_reference(recording, transform) if len(recording) else []
        assert sorted(as_tuples(out)) == expected

    assert_batches_on_both_paths(transform, rng, SENSOR, 300, check)


def test_beta_one_and_zero_without_leak_or_memory(rng):
    arr = random_stream(rng, 600, SENSOR, t_max=500)
    for tau in (math.inf, 1e-9):
        transform = LIFPooling(SENSOR, factor=(2, 3), dt=5, tau=tau, weight=0.4)
        compiled, eager = both_paths(lambda transform=transform: transform(arr))
        assert_identical(compiled, eager)


@pytest.mark.parametrize("settings", LIF_SETTINGS)
def test_the_state_is_the_same_bit_for_bit(settings, rng):
    """The membranes after a step: float32 rounded as the eager rounds round them (a fused or
    float64 update would differ in the last place long before it changed a spike)."""
    arr = random_stream(rng, 3000, SENSOR, t_max=900)
    events = Events.from_columns(arr["x"], arr["y"], arr["t"], arr["p"])
    pooling = LIFPooling(SENSOR, factor=(3, 2), dt=2, **settings)
    method, step_settings = pooling.method, pooling.settings

    def step():
        state = method.init_state(step_settings, events)
        return method.step(events, state, step_settings)

    (out_compiled, compiled), (out_eager, eager) = both_paths(step)
    assert_identical(out_compiled, out_eager)
    assert_identical(tuple(compiled.neurons), tuple(eager.neurons))
    assert bool((compiled.neurons.last_step >= 0).any())
    assert (compiled.decided, int(compiled.t_start), int(compiled.last_t)) == (
        eager.decided, int(eager.t_start), int(eager.last_t))
    assert_identical(compiled.pending, eager.pending)


@pytest.mark.parametrize(("factor", "batch"), [((4, 2), 1), ((3, 2), 1), ((3, 2), 3), ((1, 1), 2)])
def test_counted_cells_equal_the_eager_count(factor, batch, rng):
    # A live chunk's cells (many events on few keys), counted in pieces (a session's pending
    # events, then its chunk's): the compiled pass gives the eager keys and counts, with
    # region shifts (powers of two) or tables, for stacked recordings too.
    keys = importlib.import_module("evdown_torch.transforms.functional.lif.keys")
    steps_module = importlib.import_module("evdown_torch.transforms.functional.lif.steps")
    fx, fy = factor
    wo, ho = math.ceil(12 / fx), math.ceil(10 / fy)
    n, low, span = 30_000, 2**33 + 7, 9
    x, y = rng.integers(0, 12, n), rng.integers(0, 10 * batch, n)
    steps = torch.from_numpy(np.sort(rng.integers(low, low + span, n)))
    p = rng.random(n) < 0.4
    pieces = [(Events.from_columns(x[part], y[part], steps[part], p[part]), steps[part])
              for part in (slice(0, 1_000), slice(1_000, n))]
    kwargs = dict(fx=fx, fy=fy, wo=wo, plane=batch * wo * ho, low=low, span=span)
    compiled, eager = both_paths(lambda: keys.counted_cells(pieces, **kwargs))
    assert_identical(compiled, eager)
    # the chunk's steps as runs (a live session's): the same cells on both paths
    chunk_steps = steps[1_000:]
    first = int(chunk_steps[0])
    runs = steps_module.StepRuns(first, torch.bincount(chunk_steps - first))
    assert torch.equal(runs.expand(), chunk_steps)
    as_runs = [pieces[0], (pieces[1][0], runs)]
    for path in both_paths(lambda: keys.counted_cells(as_runs, **kwargs)):
        assert_identical(path, compiled)
    cell_key, counts = compiled
    assert int(counts.sum()) == n and bool((counts.sum(1) > 0).all())
    # one hand-checked cell: the first event's
    key = ((int(x[0]) // fx) + (int(y[0]) // fy) * wo) * span + int(steps[0]) - low
    assert int(counts[int(torch.searchsorted(cell_key, key))].sum()) == int(
        ((torch.from_numpy(x) // fx + torch.from_numpy(y) // fy * wo) * span
         + steps - low == key).sum())


def test_counted_cells_refuse_a_step_outside_their_span():
    keys = importlib.import_module("evdown_torch.transforms.functional.lif.keys")
    events = Events.from_columns([0, 1, 2], [0, 0, 1], [0, 1, 2], [1, 0, 1])
    steps = torch.tensor([5, 6, 9])
    with eager_kernels(False), pytest.raises(ValueError, match=r"event 2 .* steps 5\.\.8"):
        keys.counted_cells([(events, steps)], fx=2, fy=2, wo=2, plane=4, low=5, span=4)


def test_long_chains_in_several_regions_each_take_the_eager_round_on_their_cell(monkeypatch):
    # Chains the loop cannot follow (past EXACT_CHAIN_STEPS) in three regions: each such cell,
    # wherever it lies among the cells, is the eager round's, on that cell alone, and the
    # loop goes on after it.
    eager_rounds = spy(monkeypatch, ROUNDS, "_round")
    strong = LIFPooling(SENSOR, factor=2, dt=1, tau=40.0, weight=3.0)
    chain = np.zeros(15, dtype=random_stream(np.random.default_rng(0), 1, SENSOR).dtype)
    chain["t"] = [0] * 4 + [1] * 4 + [2] * 4 + [50, 60, 200]
    chain["x"] = [0] * 4 + [2] * 4 + [4] * 4 + [2, 4, 9]
    chain["p"] = True
    compiled, eager = both_paths(lambda: strong(chain))
    assert_identical(compiled, eager)
    assert sorted(as_tuples(compiled)) == lif_dense_reference(chain, strong)
    with eager_kernels(False):
        eager_rounds.clear()
        strong(chain)
    assert len(eager_rounds) == 2  # the cells at t = 50 and 60 (cells 2 and 4 of 6)


@pytest.mark.parametrize("table", [True, False])
@pytest.mark.parametrize("from_step", [0, 23])
def test_spikes_by_step_equal_the_eager_ones(table, from_step, monkeypatch, rng):
    # Spikes at cells and runs through the steps after them, some before from_step (dropped),
    # some runs straddling it (cut): both paths give the spikes of a slow reference, ordered
    # by step, then neuron, by the table or by the sort.
    keys = importlib.import_module("evdown_torch.transforms.functional.lif.keys")
    chains = importlib.import_module("evdown_torch.transforms.functional.lif.chains")
    if not table:
        monkeypatch.setattr(keys, "TABLE_KEYS_PER_SPIKE", 0)
    plane, per_region = 30, 5
    cell_region = torch.arange(plane).repeat_interleave(per_region)
    cell_step = torch.tensor([10 * j + r % 3 for r in range(plane) for j in range(per_region)])
    fired = torch.from_numpy(rng.random((plane * per_region, 2)) < 0.4)
    spike_cell, spike_polarity = fired.nonzero(as_tuple=True)
    run_cell = torch.from_numpy(rng.choice(plane * per_region, 40, replace=False))
    run_polarity = torch.from_numpy(rng.integers(0, 2, 40))
    run_start = cell_step[run_cell] + 1
    run_length = torch.from_numpy(rng.integers(0, 9, 40))  # within the 9 steps to the next cell
    spikes = chains.CellSpikes(spike_cell, spike_polarity, run_cell, run_polarity, run_start,
                               run_length)
    want = sorted(
        [(int(cell_step[c]), int(cell_region[c]) + int(p) * plane)
         for c, p in zip(spike_cell, spike_polarity, strict=True)]
        + [(s, int(cell_region[c]) + int(p) * plane)
           for c, p, s0, n in zip(run_cell, run_polarity, run_start, run_length, strict=True)
           for s in range(int(s0), int(s0) + int(n))])
    want = [key for key in want if key[0] >= from_step]
    tables = spy(monkeypatch, CELLS, "_by_table")
    compiled, eager = both_paths(lambda: keys.spikes_by_step(
        spikes, cell_step, cell_region, plane=plane, from_step=from_step, top_step=50))
    assert_identical(compiled, eager)
    assert len(tables) == table  # the compiled path's table, or the sort
    assert list(zip(compiled[0].tolist(), compiled[1].tolist(), strict=True)) == want
    assert len(want) > 100
    with evdown_torch.max_output_events(len(want) - 1):
        for eager_path in (False, True):
            with eager_kernels(eager_path), pytest.raises(ValueError, match=f"{len(want):,}"):
                keys.spikes_by_step(spikes, cell_step, cell_region, plane=plane,
                                    from_step=from_step, top_step=50)


@pytest.mark.parametrize("settings", LIF_SETTINGS)
def test_spikes_and_runs_equal_the_eager_ones_in_order(settings, monkeypatch, rng):
    # The spikes at cells, the runs the membranes' loop found and the tails, for every reset:
    # the compiled pass and the eager one give the same CellSpikes, element for element.
    pooling = importlib.import_module("evdown_torch.transforms.functional.lif.pooling")
    arguments = []
    real = ROUNDS.spikes_and_runs

    def record(*args, **kwargs):
        arguments.append((args, kwargs))
        return real(*args, **kwargs)

    monkeypatch.setattr(pooling, "spikes_and_runs", record)
    arr = bursty_stream(rng, 60, SENSOR, gap_max=200)
    with eager_kernels(False):
        LIFPooling(SENSOR, factor=(3, 2), dt=2, **settings)(arr)
    (args, kwargs), = arguments
    compiled, eager = both_paths(lambda: ROUNDS.spikes_and_runs(*args, **kwargs))
    assert_identical(tuple(compiled), tuple(eager))
    assert compiled.spike_cell.numel() > 0
    if settings.get("reset_mechanism") != "zero" and settings["weight"] >= 1:
        assert compiled.run_cell.numel() > 0  # strong input fires on through empty steps


@pytest.mark.parametrize("chains", [True, False])
def test_state_cells_merged_as_the_eager_merge(chains, rng):
    # Regions with cells and an earlier update, regions firing on without cells (a state
    # cell with chains only), regions never updated (none): the compiled merge and the eager
    # one give the same cells; without any state cell, the cells come back as they were.
    pooling = importlib.import_module("evdown_torch.transforms.functional.lif.pooling")
    plane, threshold = 40, 1.0
    cell_region = torch.from_numpy(np.sort(rng.choice(plane, 60)))
    cell_step = torch.from_numpy(rng.integers(10, 20, 60))
    current = torch.from_numpy(rng.random((60, 2), dtype=np.float32))
    state = pooling.LIFState(torch.from_numpy(rng.random((plane, 2), dtype=np.float32) * 2),
                             torch.from_numpy(rng.integers(-1, 9, plane)))

    def merge(state=state):
        return pooling._with_state_cells(cell_region, cell_step, current, state, plane=plane,
                                         chains=chains, threshold32=torch.tensor(threshold))

    compiled, eager = both_paths(merge)
    assert_identical(compiled, eager)
    updated = state.last_step >= 0
    above = (state.membrane > threshold).any(1) if chains else torch.zeros(plane, dtype=bool)
    has_cells = torch.zeros(plane, dtype=torch.bool)
    has_cells[cell_region] = True
    assert compiled[0].shape[0] == 60 + int(((has_cells | above) & updated).sum())
    assert bool((torch.diff(compiled[0]) >= 0).all())
    rest = pooling.initial_state(plane)  # nothing updated before: no state cell
    compiled, eager = both_paths(lambda: merge(rest))
    assert_identical(compiled, eager)
    assert all(a is b for a, b in zip(compiled, (cell_region, cell_step, current), strict=True))
