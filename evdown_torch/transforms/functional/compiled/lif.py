"""LIF pooling's compiled loops: a live chunk's cells counted, and snntorch's float32 rounds.

**Cells.** :func:`counted_cells` counts the events of every ``(region, step)`` key in one
pass, as :func:`~evdown_torch.transforms.functional.lif.keys.counted_cells` does with a few
int32 tensor passes and a ``bincount``; the same keys and counts (integers: exact).

**Membranes.** The eager kernel
(:func:`~evdown_torch.transforms.functional.lif.rounds.membranes_by_rounds`) updates the
``r``-th cell of every region at once, a fixed few tensor operations per round, on cells
reordered by round. Each neuron's updates depend only on its own region's earlier cells, so
this loop (:func:`cells_until_chain`) takes the cells as they come, region by region and step
by step, with the same float32 operations in the same order (a product, a sum, a difference:
each rounded once, as torch rounds them), reading the same decays ``beta ** g`` (computed
once for every cell by :mod:`~evdown_torch.transforms.functional.lif.powers`); no reordering.
A neuron that goes on firing through empty steps (reset "subtract") runs the first steps of
its chain as :meth:`~evdown_torch.transforms.functional.lif.chains.Leak.fire_through` runs
them (its :data:`~evdown_torch.transforms.functional.lif.chains.EXACT_CHAIN_STEPS` float32
steps), then decays by the power of the steps left, read from the same table of powers
(:attr:`~evdown_torch.transforms.functional.lif.powers.Powers.small_float32`). A cell at
which a chain outlasts those steps (the closed form's) or decays over ``2 ** LOW_BITS`` steps
or more is left to the eager round (run on that cell alone); the loop then continues after
it. Both paths give the same membranes, bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import (
    columns_of,
    power_of_two_shifts,
    region_tables,
)
from evdown_torch.transforms.functional.compiled.scratch import scratch_column
from evdown_torch.transforms.functional.lif.chains import EXACT_CHAIN_STEPS

if TYPE_CHECKING:
    from evdown_torch.events import Events
    from evdown_torch.transforms.functional.lif.chains import CellSpikes, Leak

__all__ = ["cells_until_chain", "counted_cells", "spikes_by_step"]


@compiled_loop
def _count_loop(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, steps: np.ndarray, column: np.ndarray,
    row: np.ndarray, shift_x: int, shift_y: int, wo: int, low: int, span: int,
    counts: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Adds each event to ``counts[2 * key + p]``, ``key = region * span + step - low``.

    The region ``(x >> shift_x) + (y >> shift_y) * wo`` (factors that are powers of two) or,
    with negative shifts, ``column[x] + row[y] * wo``.

    Returns:
        -1, or the first event outside the tables or the steps ``low .. low + span - 1`` (it
        and the events after it are not counted).
    """
    width = column.shape[0]
    height = row.shape[0]
    for i in range(np.uint64(0), np.uint64(x.shape[0])):
        xi = x[i]
        yi = y[i]
        step = steps[i] - low
        if xi < 0 or xi >= width or yi < 0 or yi >= height or step < 0 or step >= span:
            return np.int64(i)
        if shift_x >= 0:
            region = (xi >> shift_x) + (yi >> shift_y) * wo
        else:
            region = column[xi] + row[yi] * wo
        counts[np.uint64(2 * (region * span + step) + (1 if p[i] else 0))] += 1
    return -1


@compiled_loop
def _occupied_loop(
    counts: np.ndarray, cell_key: np.ndarray, cell_counts: np.ndarray
) -> int:  # pragma: no cover - compiled
    """The keys with events, in key order, and their ``(OFF, ON)`` counts; returns how many.

    ``cell_key`` and ``cell_counts`` of length 0: only counts them.
    """
    k = 0
    write = cell_key.shape[0] > 0
    for key in range(counts.shape[0] // 2):
        off = counts[2 * key]
        on = counts[2 * key + 1]
        if off or on:
            if write:
                cell_key[k] = key
                cell_counts[k, 0] = off
                cell_counts[k, 1] = on
            k += 1
    return k


def counted_cells(
    pieces: Sequence[tuple[Events, Tensor]], *, fx: int, fy: int, wo: int, plane: int,
    low: int, span: int,
) -> tuple[Tensor, Tensor]:
    """:func:`~evdown_torch.transforms.functional.lif.keys.counted_cells` on the CPU, compiled.

    The same arguments (CPU tensors) and the same ``(cell_key, counts)``: int64 sorted keys
    of the cells and their ``(n_cells, 2)`` int64 OFF and ON counts (new tensors).

    Raises:
        ValueError: for an event outside the ``plane // wo`` rows of ``wo`` regions, or a
            step outside ``low .. low + span - 1``.
    """
    rows = plane // wo
    column, row = region_tables((fx, fy), wo, rows)
    shift_x, shift_y = power_of_two_shifts((fx, fy))
    counts = scratch_column("lif counts", 2 * plane * span, np.int64)
    counts.fill(0)
    for events, steps in pieces:  # (a session's pending events and its new chunk's)
        x, y, p, step = columns_of(events.x, events.y, events.p, steps)
        bad = _count_loop(x, y, p, step, column, row, shift_x, shift_y, wo, low, span, counts)
        if bad >= 0:
            raise ValueError(
                f"event {bad} at (x={int(x[bad])}, y={int(y[bad])}, step {int(step[bad])}) "
                f"lies outside the {wo * fx} x {rows * fy} pixels or steps {low}.."
                f"{low + span - 1} the cells were counted over")
    empty = np.empty(0, dtype=np.int64)
    n_cells = _occupied_loop(counts, empty, empty.reshape(0, 2))
    cell_key = np.empty(n_cells, dtype=np.int64)
    cell_counts = np.empty((n_cells, 2), dtype=np.int64)
    _occupied_loop(counts, cell_key, cell_counts)
    return torch.from_numpy(cell_key), torch.from_numpy(cell_counts)

#: The loop's code of each reset mechanism.
_RESETS = {"subtract": 0, "zero": 1, "none": 2}


@compiled_loop
def _chain(
    u: np.float32, gap: int, beta: np.float32, threshold: np.float32, powers: np.ndarray,
    exact_steps: int,
) -> tuple[bool, int, np.float32, bool]:  # pragma: no cover - compiled
    """``Leak.fire_through`` of a neuron that fired (``u > threshold``), then ``gap >= 1`` steps.

    Returns:
        ``(ok, count, w, still)``: ``ok`` False where the loop cannot follow the eager chain
        (it outlasts ``exact_steps`` steps, or the decay after it is not in ``powers``); else
        the spikes fired in the gap, the membrane after it and whether it fired at its end.
    """
    v = u
    steps = 0
    count = 0
    alive = True
    for j in range(exact_steps):
        if not alive:
            break
        v = beta * v - threshold  # + a zero current: exact
        steps += 1
        alive = v > threshold
        if alive:
            count += 1
        alive = alive and gap > j + 1
    if alive or gap - steps >= powers.shape[0]:
        return False, 0, v, False
    return True, count, v * powers[gap - steps], bool(v > threshold)


@compiled_loop
def _membranes_loop(
    membrane: np.ndarray, current: np.ndarray, decay: np.ndarray, decay_after_one: np.ndarray,
    gap: np.ndarray, first: np.ndarray, chain_count: np.ndarray, start: int, beta: np.float32,
    threshold: np.float32, reset: int, powers: np.ndarray, exact_steps: int,
) -> int:  # pragma: no cover - compiled
    """Cells ``start, start + 1, ...`` (by region, then step) updated in place in ``membrane``.

    ``membrane``, ``current``: ``(n, 2)`` float32; ``decay``, ``decay_after_one``: ``(n,)``
    float32 ``beta ** g`` and ``beta ** (g - 1)`` of the gap ``g`` (``gap``) before each
    cell; ``first``: a region's first cell (its membrane is its current: ``beta * 0 + I``);
    ``chain_count``: ``(n, 2)`` int64, the spikes of a firing chain in the gap are written
    there. ``reset``: 0 subtract, 1 zero, 2 none.

    Returns:
        ``n``, or the first cell (not computed) whose firing chain the loop cannot follow
        (:func:`_chain`).
    """
    zero = np.float32(0.0)
    for i in range(start, membrane.shape[0]):
        if first[i]:
            membrane[i, 0] = current[i, 0]
            membrane[i, 1] = current[i, 1]
            continue
        silent = gap[i] > 0
        if reset == 0 and silent:
            for c in range(2):
                u = membrane[i - 1, c]
                if u > threshold and beta * u - threshold > threshold:
                    ok, _, _, _ = _chain(u, gap[i], beta, threshold, powers, exact_steps)
                    if not ok:
                        return i
        for c in range(2):
            u = membrane[i - 1, c]
            fired = u > threshold
            w = u * decay[i]
            if reset == 1:
                if fired:
                    w = zero
            elif reset == 0 and fired and silent:  # one step of the chain, then decay
                chain = beta * u - threshold
                w = chain * decay_after_one[i]
                fired = False
                if chain > threshold:  # the chain goes on: Leak.fire_through's steps
                    _, count, w, fired = _chain(u, gap[i], beta, threshold, powers,
                                                exact_steps)
                    chain_count[i, c] = count
            out = beta * w
            out = out + current[i, c]
            if reset == 0 and fired:
                out = out - threshold
            membrane[i, c] = out
    return membrane.shape[0]


def cells_until_chain(
    membrane: Tensor, current: Tensor, decay: Tensor, decay_after_one: Tensor, gap: Tensor,
    first: Tensor, chain: Tensor, *, start: int, leak: Leak,
) -> int:
    """The update at cells ``start, start + 1, ...``, compiled, up to one it cannot follow.

    Args:
        membrane: ``(n, 2)`` float32 membranes after each cell's update, written in place
            from cell ``start`` on (those before it are read).
        current: ``(n, 2)`` float32 input currents of the cells' (OFF, ON) neurons, cells
            sorted by region, then step.
        decay: ``(n, 1)`` float32 ``beta ** g`` of the gap ``g`` before each cell.
        decay_after_one: ``(n, 1)`` float32 ``beta ** (g - 1)`` (``beta ** 0`` for ``g = 0``).
        gap: ``(n, 1)`` int64 empty steps before each cell.
        first: ``(n,)`` bool, a region's first cell.
        chain: ``(n, 2)`` int64 spikes fired in the gap before each cell by a neuron that
            went on firing (reset "subtract"), written in place.
        start: the first cell to compute.
        leak: the neurons' ``beta``, threshold and reset.

    Returns:
        ``n`` when all are computed, else the first cell not computed (one with a firing
        chain longer than ``EXACT_CHAIN_STEPS`` steps, or decaying over ``2 ** LOW_BITS``
        steps or more after its chain: the eager round's).
    """
    return int(_membranes_loop(
        membrane.numpy(), current.numpy(), decay.numpy().reshape(-1),
        decay_after_one.numpy().reshape(-1), gap.numpy().reshape(-1), first.numpy(),
        chain.numpy(), start, np.float32(leak.beta), np.float32(leak.threshold),
        _RESETS[leak.reset], leak.powers.small_float32.numpy(), EXACT_CHAIN_STEPS,
    ))


@compiled_loop
def _spike_total(
    spike_cell: np.ndarray, run_start: np.ndarray, run_length: np.ndarray,
    cell_step: np.ndarray, from_step: int,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """``(at cells, in all)``: the spikes of steps ``from_step`` on."""
    at_cells = 0
    for j in range(spike_cell.shape[0]):
        at_cells += cell_step[spike_cell[j]] >= from_step
    total = at_cells
    for j in range(run_start.shape[0]):
        total += max(0, run_start[j] + run_length[j] - max(run_start[j], from_step))
    return at_cells, total


@compiled_loop
def _spike_list(
    spike_cell: np.ndarray, spike_polarity: np.ndarray, run_cell: np.ndarray,
    run_polarity: np.ndarray, run_start: np.ndarray, run_length: np.ndarray,
    cell_step: np.ndarray, cell_region: np.ndarray, plane: int, from_step: int,
    out_step: np.ndarray, out_neuron: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Every spike of steps ``from_step`` on: its step and neuron, at cells, then by run."""
    k = 0
    for j in range(spike_cell.shape[0]):
        cell = spike_cell[j]
        if cell_step[cell] >= from_step:
            out_step[k] = cell_step[cell]
            out_neuron[k] = cell_region[cell] + spike_polarity[j] * plane
            k += 1
    for j in range(run_start.shape[0]):
        neuron = cell_region[run_cell[j]] + run_polarity[j] * plane
        for step in range(max(run_start[j], from_step), run_start[j] + run_length[j]):
            out_step[k] = step
            out_neuron[k] = neuron
            k += 1


@compiled_loop
def _by_table(
    step: np.ndarray, neuron: np.ndarray, neurons: int, low: int, marked: np.ndarray,
    out_step: np.ndarray, out_neuron: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The distinct keys ``(step - low) * neurons + neuron`` marked, then read in order."""
    marked[:] = False
    for j in range(step.shape[0]):
        marked[np.uint64((step[j] - low) * neurons + neuron[j])] = True
    k = 0
    for key in range(marked.shape[0]):
        if marked[key]:
            out_step[k] = key // neurons + low
            out_neuron[k] = key % neurons
            k += 1


def spikes_by_step(
    spikes: CellSpikes, cell_step: Tensor, cell_region: Tensor, *, plane: int, from_step: int,
    top_step: int,
) -> tuple[Tensor, Tensor]:
    """:func:`~evdown_torch.transforms.functional.lif.keys.spikes_by_step` on the CPU, compiled.

    The same arguments (CPU tensors), checks and ``(spike_step, neuron)`` (new tensors).
    Where the keys ``(step, neuron)`` are few next to the spikes
    (:data:`~evdown_torch.transforms.functional.lif.keys.TABLE_KEYS_PER_SPIKE`), a compiled
    table orders them; else :func:`~evdown_torch.transforms.functional.lif.keys.
    by_step_then_neuron`'s sort.
    """
    from evdown_torch.transforms.functional.lif.keys import (
        TABLE_KEYS_PER_SPIKE,
        by_step_then_neuron,
        check_spike_count,
    )

    spike_cell, spike_polarity, run_cell, run_polarity, run_start, run_length = (
        columns_of(*spikes))
    steps, regions = columns_of(cell_step, cell_region)
    at_cells, total = _spike_total(spike_cell, run_start, run_length, steps, from_step)
    check_spike_count(total, at_cells)
    if total == 0:
        return torch.empty(0, dtype=torch.int64), torch.empty(0, dtype=torch.int64)
    step = np.empty(total, dtype=np.int64)
    neuron = np.empty(total, dtype=np.int64)
    _spike_list(spike_cell, spike_polarity, run_cell, run_polarity, run_start, run_length,
                steps, regions, plane, from_step, step, neuron)
    neurons = 2 * plane
    n_keys = (top_step - from_step + 1) * neurons
    if n_keys > TABLE_KEYS_PER_SPIKE * total:
        return by_step_then_neuron(torch.from_numpy(step), torch.from_numpy(neuron), neurons,
                                   from_step, top_step)
    out_step = np.empty(total, dtype=np.int64)
    out_neuron = np.empty(total, dtype=np.int64)
    _by_table(step, neuron, neurons, from_step, scratch_column("lif spike keys", n_keys, np.bool_),
              out_step, out_neuron)
    return torch.from_numpy(out_step), torch.from_numpy(out_neuron)
