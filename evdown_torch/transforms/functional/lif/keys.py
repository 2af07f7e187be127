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

from evdown_torch._tensors import changes, divide, run_index, stable_sort_small, where_true
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled import use_compiled

__all__ = ["TABLE_KEYS_PER_SPIKE", "by_step_then_neuron", "counted_cells", "grouped_cells"]

#: Most ``(step, neuron)`` keys per spike for which the spikes are ordered by a table of every
#: key rather than by a sort.
TABLE_KEYS_PER_SPIKE = 16


def counted_cells(
    pieces: Sequence[tuple[Events, Tensor]], *, fx: int, fy: int, wo: int, plane: int,
    low: int, span: int,
) -> tuple[Tensor, Tensor]:
    """The occupied keys ``region * span + (step - low)`` and their events, by counting.

    Every event's key, doubled, plus its polarity, is counted (int32 arithmetic: the caller
    keeps ``2 * plane * span`` below ``2 ** 31``), piece by piece into one tensor of keys
    (the pieces' events are not joined); the keys with a count are the cells, in key order
    (by region, then step).

    Args:
        pieces: the events (any order), each with the ``(N,)`` int64 step of every event,
            ``low .. low + span - 1``.
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
    if use_compiled(pieces[0][1]):  # one compiled pass (the same keys and counts)
        from evdown_torch.transforms.functional.compiled import lif

        return lif.counted_cells(pieces, fx=fx, fy=fy, wo=wo, plane=plane, low=low, span=span)
    i32 = torch.int32
    keys = []
    for events, steps in pieces:  # (a session's pending events and its new chunk's)
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
    device = events.device
    region = divide(events.x, fx).add_(divide(events.y, fy), alpha=wo)
    n, n_keys = region.shape[0], plane * span
    cell_region = None
    if table:
        key = region.mul_(span).add_(steps).sub_(low)
        occupied = torch.zeros(n_keys, dtype=torch.bool, device=device)
        occupied[key] = True
        count_dtype = torch.int32 if n < 1 << 30 else torch.int64  # 2 * cells + 1 fits
        rank = torch.cumsum(occupied, 0, dtype=count_dtype)  # cells up to each key
        del occupied
        cell_of_event = rank.index_select(0, key).sub_(1)
        cell_step = torch.empty(int(rank[-1]), dtype=torch.int64, device=device)
        cell_step[cell_of_event] = key  # the cells' keys, sorted
        del rank
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
