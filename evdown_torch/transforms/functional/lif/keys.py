"""LIF pooling's keys: events grouped by ``(region, step)`` cell, spikes sorted by step.

Used by :func:`.pooling.lif_spikes` (see :func:`.pooling._event_cells` for which path a call
takes). Where a call's cells are few next to its events (a live chunk: a thousand regions,
ten steps, hundreds of thousands of events), the cells are found by counting every key's
events, one pass over the events in int32 (:func:`counted_cells`); otherwise by grouping them
(:func:`grouped_cells`: a table of occupied keys or a sort).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from evdown_torch._tensors import (
    changes,
    distinct_in_range,
    divide,
    run_index,
    runs_of,
    stable_sort_small,
    where_true,
)
from evdown_torch.checks import check_output_count
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.lif.chains import CellSpikes
from evdown_torch.transforms.functional.lif.steps import Steps, each_step

__all__ = ["TABLE_KEYS_PER_SPIKE", "by_step_then_neuron", "check_spike_count", "counted_cells",
           "grouped_cells", "spikes_by_step"]

#: Most ``(step, neuron)`` keys per spike for which the spikes are ordered by a table of every
#: key rather than by a sort.
TABLE_KEYS_PER_SPIKE = 16


def counted_cells(
    pieces: Sequence[tuple[Events, Steps]], *, fx: int, fy: int, wo: int, plane: int,
    low: int, span: int,
) -> tuple[Tensor, Tensor]:
    """The occupied keys ``region * span + (step - low)`` and their events, by counting.

    Every event's key, doubled, plus its polarity, is counted (int32 arithmetic: the caller
    keeps ``2 * plane * span`` below ``2 ** 31``), piece by piece into one tensor of keys
    (the pieces' events are not joined); the keys with a count are the cells, in key order
    (by region, then step).

    Args:
        pieces: the events (any order), each with the ``(N,)`` int64 step of every event,
            ``low .. low + span - 1`` (or, time-sorted, their :class:`~.steps.StepRuns`).
        fx: region width.
        fy: region height.
        wo: regions per row.
        plane: regions in all.
        low: the events' earliest step.
        span: steps per region in the key.

    Returns:
        ``(cell_key, counts)``: int64 sorted keys of the cells and their ``(n_cells, 2)``
        int64 counts of OFF and ON events.
    """
    if use_compiled(pieces[0][0].x):  # one compiled pass (the same keys and counts)
        from evdown_torch.transforms.functional.compiled import lif_cells

        return lif_cells.counted_cells(pieces, fx=fx, fy=fy, wo=wo, plane=plane, low=low, span=span)
    i32 = torch.int32
    keys = []
    for events, piece_steps in pieces:  # (a session's pending events and its new chunk's)
        steps = each_step(piece_steps)
        key = events.x.to(i32)  # in place from here: two int32 columns in all
        divide(key, fx, out=key).mul_(2 * span)
        other = events.y.to(i32)
        key.add_(divide(other, fy, out=other), alpha=2 * span * wo)
        if low + span <= 1 << 31:  # the steps themselves fit in int32
            other.copy_(steps).sub_(low)
        else:
            other.copy_(steps.sub(low))
        keys.append(key.add_(other, alpha=2).add_(events.p))
    key = keys[0] if len(keys) == 1 else torch.cat(keys)
    counts = torch.bincount(key, minlength=2 * plane * span).view(-1, 2)
    cell_key = where_true(counts.any(1))
    return cell_key, counts.index_select(0, cell_key)


def grouped_cells(
    events: Events, steps: Tensor, *, fx: int, fy: int, wo: int, plane: int, low: int,
    span: int, table: bool,
) -> tuple[Tensor | None, Tensor, Tensor]:
    """The cells by grouping the events: ``(cell_region, cell_key, counts)``.

    A table of the keys (``table``; the keys ``region * span + step - low`` must then fit in
    int64), else a sort of them where they fit, else a stable sort of the regions (events in
    time order); ``cell_region`` is
    ``None`` except from the stable sort, which gives the cells' steps in place of their keys;
    ``counts`` are the cells' ``(n_cells, 2)`` int64 OFF and ON events.
    """
    region = divide(events.x, fx).add_(divide(events.y, fy), alpha=wo)
    n_keys = plane * span
    cell_region = None
    if table:
        key = region.mul_(span).add_(steps).sub_(low)
        cell_step, cell_of_event = distinct_in_range(key, 0, n_keys - 1)  # the cells' keys
        polarity = events.p
    elif n_keys < 1 << 62:
        key, order = torch.sort(region.mul_(span).add_(steps).sub_(low))
        polarity = events.p.index_select(0, order)
        del order
        starts = changes(key)
        cell_of_event = run_index(starts)
        cell_step = key.index_select(0, where_true(starts))
    else:
        region, order = stable_sort_small(region, plane)  # stable: time order within a region
        steps = steps.index_select(0, order)
        polarity = events.p.index_select(0, order)
        del order
        starts = changes(region)
        starts[1:] |= steps[1:] != steps[:-1]
        cell_of_event = run_index(starts)
        first = where_true(starts)
        cell_region, cell_step = region.index_select(0, first), steps.index_select(0, first)
        del region, steps, starts, first
    n_cells = cell_step.shape[0]
    counts = torch.bincount(cell_of_event.mul_(2).add_(polarity), minlength=2 * n_cells)
    return cell_region, cell_step, counts.view(n_cells, 2)


def by_step_then_neuron(
    spike_step: Tensor, neuron: Tensor, neurons: int, low: int, top: int
) -> tuple[Tensor, Tensor]:
    """Spikes (steps ``low .. top``) sorted by step, then neuron (``neurons`` of them).

    A neuron fires at most once per step, so the keys ``(step - low) * neurons + neuron`` are
    distinct: where they are few next to the spikes (:data:`TABLE_KEYS_PER_SPIKE`) the sorted
    keys are the marked entries of a table of every key, without a sort (a live chunk's
    15k spikes: 0.1 ms instead of 0.8); else one sort of the key where it fits in int64, else
    by neuron, then stably by step.
    """
    n_keys = (top - low + 1) * neurons
    if n_keys <= TABLE_KEYS_PER_SPIKE * spike_step.shape[0]:
        if use_compiled(spike_step):  # one compiled pass over the table
            from evdown_torch.transforms.functional.compiled import lif_cells

            return lif_cells.by_table(spike_step, neuron, neurons, low, n_keys)
        marked = torch.zeros(n_keys, dtype=torch.bool, device=spike_step.device)
        marked[(spike_step - low).mul_(neurons).add_(neuron)] = True
        key = where_true(marked)
        step = divide(key, neurons)
        return step + low, key.sub_(step * neurons)
    if (top + 1) * neurons < 1 << 62:
        order = torch.sort(spike_step * neurons + neuron).indices
    else:
        _, order = stable_sort_small(neuron, neurons)
        spike_step, neuron = spike_step[order], neuron[order]
        order = torch.sort(spike_step, stable=True).indices
    return spike_step[order], neuron[order]


def check_spike_count(total: int, at_cells: int) -> None:
    """Refuse ``total`` spikes (``at_cells`` of them at cells) past the output limit in force."""
    check_output_count(
        total, detail=f" ({total - at_cells:,} of them fired by LIF neurons that stay "
        "above threshold through silent steps)", fewer="a lower weight gives fewer events")


def spikes_by_step(
    spikes: CellSpikes, cell_step: Tensor, cell_region: Tensor, *, plane: int, from_step: int,
    top_step: int,
) -> tuple[Tensor, Tensor]:
    """A call's spikes of steps ``from_step .. top_step``, one by one, by step, then neuron.

    The spikes at cells and the runs' spikes (one per step of a run), less those of steps
    before ``from_step`` (returned by an earlier call: neither built nor counted), counted
    first (:func:`check_spike_count`), then sorted (:func:`by_step_then_neuron`). On the CPU
    compiled loops count and build them
    (:mod:`evdown_torch.transforms.functional.compiled.lif_cells`): the same spikes.

    Args:
        spikes: the call's :class:`~.chains.CellSpikes`.
        cell_step: ``(n,)`` int64 step of every cell.
        cell_region: ``(n,)`` int64 region of every cell (``0 .. plane - 1``).
        plane: regions in all; a neuron is ``polarity * plane + region``.
        from_step: the first step to return.
        top_step: the last step a spike can lie in.

    Returns:
        ``(spike_step, neuron)``: int64, sorted by step, then neuron.

    Raises:
        ValueError: when the spikes exceed the output limit in force.
    """
    if use_compiled(cell_step):  # compiled passes: the same spikes
        from evdown_torch.transforms.functional.compiled import lif_cells

        at_cells, total = lif_cells.spike_counts(spikes, cell_step, from_step)
        check_spike_count(total, at_cells)
        spike_step, neuron = lif_cells.spike_list(spikes, cell_step, cell_region, plane=plane,
                                                  from_step=from_step, total=total)
        return by_step_then_neuron(spike_step, neuron, 2 * plane, from_step, top_step)
    spike_cell, spike_polarity, run_cell, run_polarity, run_start, run_length = spikes
    spike_step = cell_step.index_select(0, spike_cell)
    if from_step > 0:  # drop the spikes of steps an earlier call returned
        keep = spike_step >= from_step
        spike_cell, spike_polarity = spike_cell[keep], spike_polarity[keep]
        spike_step = spike_step[keep]
        run_end = run_start + run_length
        run_start = run_start.clamp(min=from_step)
        run_length = (run_end - run_start).clamp_(min=0)
    total = spike_cell.shape[0] + (int(run_length.sum()) if run_length.shape[0] else 0)
    check_spike_count(total, spike_cell.shape[0])
    if run_length.shape[0]:  # the spikes of the runs, one by one
        run_of_spike = runs_of(run_length, total - spike_cell.shape[0])
        first_of_run = torch.cumsum(run_length, 0) - run_length
        within_run = (torch.arange(run_of_spike.shape[0], device=cell_step.device)
                      - first_of_run[run_of_spike])
        spike_step = torch.cat([spike_step, run_start[run_of_spike] + within_run])
        spike_cell = torch.cat([spike_cell, run_cell[run_of_spike]])
        spike_polarity = torch.cat([spike_polarity, run_polarity[run_of_spike]])
    neuron = torch.add(cell_region.index_select(0, spike_cell), spike_polarity, alpha=plane)
    # a neuron fires at most once per step: the keys are distinct
    return by_step_then_neuron(spike_step, neuron, 2 * plane, from_step, top_step)
