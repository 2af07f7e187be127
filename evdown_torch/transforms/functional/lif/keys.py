"""LIF pooling's keys: events counted by ``(region, step)`` cell, spikes sorted by step.

Used by :func:`.pooling.lif_spikes`. Where a call's cells are few next to its events (a live
chunk: a thousand regions, ten steps, hundreds of thousands of events), the cells are found by
counting every key's events, one pass over the events in int32
(:func:`counted_cells`), rather than by a table of occupied keys or a sort.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evdown_torch._tensors import divide, stable_sort_small
from evdown_torch.events import Events

__all__ = ["TABLE_KEYS_PER_SPIKE", "by_step_then_neuron", "counted_cells"]

#: Most ``(step, neuron)`` keys per spike for which the spikes are ordered by a table of every
#: key rather than by a sort.
TABLE_KEYS_PER_SPIKE = 16


def counted_cells(
    events: Events, steps: Tensor, *, fx: int, fy: int, wo: int, plane: int, low: int,
    span: int,
) -> tuple[Tensor, Tensor]:
    """The occupied keys ``region * span + (step - low)`` and their events, by counting.

    Every event's key, doubled, plus its polarity, is counted (int32 arithmetic: the caller
    keeps ``2 * regions * span`` below ``2 ** 31``); the keys with a count are the cells, in
    key order (by region, then step).

    Args:
        events: ``N`` events (any order).
        steps: ``(N,)`` int64 step of every event, ``low .. low + span - 1``.
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
    i32 = torch.int32
    key = divide(events.x.to(i32), fx).mul_(2 * span)
    key.add_(divide(events.y.to(i32), fy), alpha=2 * span * wo)
    key.add_(steps.sub(low).to(i32), alpha=2).add_(events.p)
    counts = torch.bincount(key, minlength=2 * plane * span).view(-1, 2)
    cell_key = counts.any(1).nonzero().squeeze(1)
    return cell_key, counts.index_select(0, cell_key)


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
        key = marked.nonzero().squeeze(1)
        step = divide(key, neurons)
        return step + low, key.sub_(step * neurons)
    if (top + 1) * neurons < 1 << 62:
        order = torch.sort(spike_step * neurons + neuron).indices
    else:
        _, order = stable_sort_small(neuron, neurons)
        spike_step, neuron = spike_step[order], neuron[order]
        order = torch.sort(spike_step, stable=True).indices
    return spike_step[order], neuron[order]
