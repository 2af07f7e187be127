"""LIF pooling's compiled bookkeeping: cells counted, merged with the state, spikes ordered.

Integer work around the neurons' arithmetic (:mod:`.lif`), each the compiled twin of an eager
step of :func:`~evdown_torch.transforms.functional.lif.pooling.lif_spikes`, with the same
results (integers and copied floats: exact):

* :func:`counted_cells` counts the events of every ``(region, step)`` key in one pass, as
  :func:`~evdown_torch.transforms.functional.lif.keys.counted_cells` does with a few int32
  tensor passes and a ``bincount``;
* :func:`with_state_cells` puts each region's last update in front of its cells, as
  :func:`~evdown_torch.transforms.functional.lif.pooling._with_state_cells` does with a sort;
* :func:`spike_counts` and :func:`spike_list` count a call's spikes and build them one by
  one, and :func:`by_table` orders them by step, then neuron, as
  :func:`~evdown_torch.transforms.functional.lif.keys.spikes_by_step` and
  :func:`~evdown_torch.transforms.functional.lif.keys.by_step_then_neuron` do.
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
    region_xy,
)
from evdown_torch.transforms.functional.compiled.scratch import scratch_column
from evdown_torch.transforms.functional.lif.steps import StepRuns, Steps, each_step

if TYPE_CHECKING:
    from evdown_torch.events import Events
    from evdown_torch.transforms.functional.lif.chains import CellSpikes

__all__ = ["by_table", "counted_cells", "spike_counts", "spike_list", "with_state_cells"]


@compiled_loop
def _count_loop(
    x: np.ndarray, y: np.ndarray, p: np.ndarray, steps: np.ndarray, first: int,
    ends: np.ndarray, column: np.ndarray, row: np.ndarray, shift_x: int, shift_y: int,
    wo: int, low: int, span: int, counts: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Adds each event to ``counts[2 * key + p]``, ``key = region * span + step - low``.

    The step of event ``i`` is ``steps[i]``, or, with ``steps`` empty, ``first + r`` for
    the events ``ends[r - 1] .. ends[r] - 1`` of run ``r`` (:class:`~..lif.steps.StepRuns`).
    The region ``(x >> shift_x) + (y >> shift_y) * wo`` (factors that are powers of two) or,
    with negative shifts, ``column[x] + row[y] * wo``.

    Returns:
        -1, or the first event outside the tables or the steps ``low .. low + span - 1`` (it
        and the events after it are not counted).
    """
    width = column.shape[0]
    height = row.shape[0]
    each = steps.shape[0] > 0
    runs = 1 if each else ends.shape[0]
    start = 0
    for r in range(runs):
        stop = x.shape[0] if each else ends[r]
        for i in range(np.uint64(start), np.uint64(stop)):
            xi = x[i]
            yi = y[i]
            step = (steps[i] if each else first + r) - low
            if xi < 0 or xi >= width or yi < 0 or yi >= height or step < 0 or step >= span:
                return np.int64(i)
            rx, ry = region_xy(xi, yi, shift_x, shift_y, column, row)
            region = rx + ry * wo
            counts[np.uint64(2 * (region * span + step) + (1 if p[i] else 0))] += 1
        start = stop
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
    pieces: Sequence[tuple[Events, Steps]], *, fx: int, fy: int, wo: int, plane: int,
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
    no_runs = np.empty(0, dtype=np.int64)
    for events, steps in pieces:  # (a session's pending events and its new chunk's)
        x, y, p = columns_of(events.x, events.y, events.p)
        if isinstance(steps, StepRuns):  # the steps of runs, not of each event
            each, first, ends = no_runs, steps.first, np.cumsum(steps.counts.numpy())
        else:
            each, first, ends = columns_of(steps)[0], 0, no_runs
        bad = _count_loop(x, y, p, each, first, ends, column, row, shift_x, shift_y, wo, low,
                          span, counts)
        if bad >= 0:
            step = int(each_step(steps)[bad])
            raise ValueError(
                f"event {bad} at (x={int(x[bad])}, y={int(y[bad])}, step {step}) "
                f"lies outside the {wo * fx} x {rows * fy} pixels or steps {low}.."
                f"{low + span - 1} the cells were counted over")
    empty = np.empty(0, dtype=np.int64)
    n_cells = _occupied_loop(counts, empty, empty.reshape(0, 2))
    cell_key = np.empty(n_cells, dtype=np.int64)
    cell_counts = np.empty((n_cells, 2), dtype=np.int64)
    _occupied_loop(counts, cell_key, cell_counts)
    return torch.from_numpy(cell_key), torch.from_numpy(cell_counts)


@compiled_loop
def _put_cell(
    out_region: np.ndarray, out_step: np.ndarray, out_current: np.ndarray, k: int,
    region: int, step: int, values: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Cell ``k`` of the merged cells: its region, step and ``(OFF, ON)`` current."""
    out_region[k] = region
    out_step[k] = step
    out_current[k, 0] = values[0]
    out_current[k, 1] = values[1]


@compiled_loop
def _merge_loop(
    cell_region: np.ndarray, cell_step: np.ndarray, current: np.ndarray,
    membrane: np.ndarray, last_step: np.ndarray, chains: bool, threshold: np.float32,
    out_region: np.ndarray, out_step: np.ndarray, out_current: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """The cells with each wanted region's state cell in front; returns how many in all.

    A region is wanted where it was updated before (``last_step >= 0``) and has cells or,
    with ``chains``, a neuron above threshold. ``out_*`` of length 0: only counts them.
    Returns -1 where the cells are not sorted by region (a guard: the callers sort them).
    """
    write = out_region.shape[0] > 0
    n = cell_region.shape[0]
    k = np.int64(0)  # (not a literal 0: one compile of _put_cell, not two)
    i = 0
    for r in range(last_step.shape[0]):
        start = i
        while i < n and cell_region[i] == r:
            i += 1
        wanted = start < i or (chains and (membrane[r, 0] > threshold
                                           or membrane[r, 1] > threshold))
        if wanted and last_step[r] >= 0:  # the state cell: its membrane as its current
            if write:
                _put_cell(out_region, out_step, out_current, k, r, last_step[r], membrane[r])
            k += 1
        for j in range(start, i):
            if write:
                _put_cell(out_region, out_step, out_current, k, r, cell_step[j], current[j])
            k += 1
    return k if i == n else -1


def with_state_cells(
    cell_region: Tensor, cell_step: Tensor, current: Tensor, state: tuple[Tensor, Tensor], *,
    chains: bool, threshold: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`~evdown_torch.transforms.functional.lif.pooling._with_state_cells` on the CPU.

    The same cells (new tensors, or the given ones where no region has a state cell): each
    region's last update, a cell at its last step whose current is its membrane, in front
    of the region's cells, in one compiled merge of the cells (sorted by region, then
    step) with the state's regions. ``state``: a :class:`~..lif.pooling.LIFState`,
    ``(membrane, last_step)``.
    """
    region, step, values = columns_of(cell_region, cell_step, current)
    membrane, last_step = columns_of(*state)
    empty = np.empty(0, dtype=np.int64)
    arguments = (region, step, values, membrane, last_step, chains, np.float32(threshold))
    total = _merge_loop(*arguments, empty, empty, np.empty((0, 2), dtype=np.float32))
    if total < 0:
        raise RuntimeError("LIF pooling's cells were not sorted by region (please report this)")
    if total == region.shape[0]:
        return cell_region, cell_step, current
    out = (np.empty(total, dtype=np.int64), np.empty(total, dtype=np.int64),
           np.empty((total, 2), dtype=np.float32))
    _merge_loop(*arguments, *out)
    return torch.from_numpy(out[0]), torch.from_numpy(out[1]), torch.from_numpy(out[2])


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
) -> int:  # pragma: no cover - compiled
    """The distinct keys ``(step - low) * neurons + neuron`` marked, then read in order.

    Returns:
        -1, or the first spike whose key lies outside the table (none can: a guard).
    """
    marked[:] = False
    for j in range(step.shape[0]):
        key = (step[j] - low) * neurons + neuron[j]
        if key < 0 or key >= marked.shape[0]:
            return j
        marked[np.uint64(key)] = True
    k = 0
    for key in range(marked.shape[0]):
        if marked[key]:
            out_step[k] = key // neurons + low
            out_neuron[k] = key % neurons
            k += 1
    return -1


def spike_counts(spikes: CellSpikes, cell_step: Tensor, from_step: int) -> tuple[int, int]:
    """``(at cells, in all)``: a call's spikes of steps ``from_step`` on (CPU tensors).

    As :func:`~evdown_torch.transforms.functional.lif.keys.spikes_by_step` counts them.
    """
    spike_cell, _, _, _, run_start, run_length = columns_of(*spikes)
    at_cells, total = _spike_total(spike_cell, run_start, run_length,
                                   columns_of(cell_step)[0], from_step)
    return int(at_cells), int(total)


def spike_list(
    spikes: CellSpikes, cell_step: Tensor, cell_region: Tensor, *, plane: int, from_step: int,
    total: int,
) -> tuple[Tensor, Tensor]:
    """The ``total`` spikes of steps ``from_step`` on (:func:`spike_counts`), one by one.

    ``(spike_step, neuron)``, int64 (new tensors), the spikes at cells first, then the runs'
    (a neuron is ``polarity * plane + region``); unordered.
    """
    step = np.empty(total, dtype=np.int64)
    neuron = np.empty(total, dtype=np.int64)
    _spike_list(*columns_of(*spikes), *columns_of(cell_step, cell_region), plane, from_step,
                step, neuron)
    return torch.from_numpy(step), torch.from_numpy(neuron)


def by_table(
    spike_step: Tensor, neuron: Tensor, neurons: int, low: int, n_keys: int
) -> tuple[Tensor, Tensor]:
    """:func:`~evdown_torch.transforms.functional.lif.keys.by_step_then_neuron`'s table, compiled.

    The distinct keys ``(step - low) * neurons + neuron`` (all below ``n_keys``) marked in a
    table, then read in order: the spikes sorted by step, then neuron (new tensors).

    Raises:
        RuntimeError: for a key outside the table (none can be: a guard against memory
            errors).
    """
    step, ids = columns_of(spike_step, neuron)
    out_step = np.empty(step.shape[0], dtype=np.int64)
    out_neuron = np.empty(step.shape[0], dtype=np.int64)
    outside = _by_table(step, ids, neurons, low, scratch_column("lif spike keys", n_keys, np.bool_),
                        out_step, out_neuron)
    if outside >= 0:
        raise RuntimeError(f"LIF pooling found a spike at step {int(step[outside])} outside the "
                           f"{n_keys // neurons} steps from {low} it computed (please report "
                           "this)")
    return torch.from_numpy(out_step), torch.from_numpy(out_neuron)
