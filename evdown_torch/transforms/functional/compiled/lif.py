"""LIF pooling's compiled loops: snntorch's float32 update cell by cell, and the cells' spikes.

(The integer bookkeeping around them, cells counted and spikes ordered: :mod:`.lif_cells`.)

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

**Spikes.** :func:`spikes_and_runs` finds the spikes at cells, the runs the loop found and
the neurons that fire on after a region's last cell in one pass, as
:func:`~evdown_torch.transforms.functional.lif.rounds.spikes_and_runs` does; a tail's length
is :meth:`~evdown_torch.transforms.functional.lif.chains.Leak.fire_through`'s float32 steps
(the closed form's past them).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from evdown_torch._tensors import where_true
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import columns_of
from evdown_torch.transforms.functional.lif.chains import EXACT_CHAIN_STEPS, CellSpikes

if TYPE_CHECKING:
    from evdown_torch.transforms.functional.lif.chains import Leak

__all__ = ["cells_until_chain", "spikes_and_runs"]

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
def _spikes_loop(
    membrane: np.ndarray, chain_before: np.ndarray, cell_step: np.ndarray,
    gap_before: np.ndarray, gap_after: np.ndarray, last: np.ndarray, threshold: np.float32,
    tails: int, out: np.ndarray,
) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """The spikes at cells, the runs the rounds found and the tails, neuron by neuron.

    ``tails``: 0 none, 1 after a region's last cell only (``last``), 2 after every cell.
    ``out``: ``(3, 4, 2 * n)`` int64; each kind (spike, run, tail), in neuron order (cell,
    then polarity), is written as rows (cell, polarity, first step, length or gap).

    Returns:
        How many of each kind.
    """
    spikes, runs, candidates = 0, 0, 0
    for i in range(membrane.shape[0]):
        for c in range(2):
            fired = membrane[i, c] > threshold
            if fired:
                out[0, 0, spikes] = i
                out[0, 1, spikes] = c
                spikes += 1
            if chain_before[i, c] > 0:
                out[1, 0, runs] = i
                out[1, 1, runs] = c
                out[1, 2, runs] = cell_step[i] - gap_before[i]
                out[1, 3, runs] = chain_before[i, c]
                runs += 1
            if fired and gap_after[i] > 0 and (tails == 2 or (tails == 1 and last[i])):
                out[2, 0, candidates] = i
                out[2, 1, candidates] = c
                out[2, 2, candidates] = cell_step[i] + 1
                out[2, 3, candidates] = gap_after[i]
                candidates += 1
    return spikes, runs, candidates


@compiled_loop
def _tail_loop(
    u: np.ndarray, gap: np.ndarray, beta: np.float32, threshold: np.float32, subtract: bool,
    exact_steps: int, count: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """The spikes of each neuron that fired (``u > threshold``), then ``gap >= 1`` empty steps.

    :meth:`~..lif.chains.Leak.fire_through`'s float32 steps (resets "subtract" and "none"),
    at most ``exact_steps`` of them; ``count`` gets -1 for a chain still firing after them
    (the closed form's).

    Returns:
        How many chains are left to the closed form.
    """
    left = 0
    for j in range(u.shape[0]):
        v = u[j]
        spikes = 0
        alive = True
        for step in range(exact_steps):
            if not alive:
                break
            v = beta * v  # + a zero current: exact
            if subtract:
                v = v - threshold
            alive = v > threshold
            if alive:
                spikes += 1
            alive = alive and gap[j] > step + 1
        count[j] = -1 if alive else spikes
        left += alive
    return left


def spikes_and_runs(
    membrane: Tensor, chain_before: Tensor, cell_step: Tensor, gap_before: Tensor,
    gap_after: Tensor, region_last: Tensor, *, leak: Leak,
) -> CellSpikes:
    """:func:`~evdown_torch.transforms.functional.lif.rounds.spikes_and_runs` on the CPU.

    The same arguments (CPU tensors) and the same :class:`~..lif.chains.CellSpikes`, in the
    same order: one compiled pass finds the spikes at cells, the runs the rounds found and
    the neurons that fire on after a cell (the tails), whose run lengths
    :meth:`~..lif.chains.Leak.fire_through` gives, as on the eager path.
    """
    n = membrane.shape[0]
    last = np.zeros(n, dtype=np.bool_)
    last[region_last.numpy()] = True
    tails = {"zero": 0, "subtract": 1, "none": 2}[leak.reset]
    columns = columns_of(membrane, chain_before, cell_step, gap_before, gap_after)
    out = np.empty((3, 4, 2 * n), dtype=np.int64)
    counts = _spikes_loop(*columns, last, np.float32(leak.threshold), tails, out)
    spike, run, tail = (torch.from_numpy(out[kind, :, :count].copy())
                        for kind, count in enumerate(counts))
    if tails:  # the tails' lengths: fire_through's float32 steps, else its closed form
        tail_u, tail_gap = membrane[tail[0], tail[1]], tail[3]
        tail_length = torch.empty_like(tail_gap)
        left = _tail_loop(tail_u.numpy(), tail_gap.numpy(), np.float32(leak.beta),
                          np.float32(leak.threshold), leak.reset == "subtract",
                          EXACT_CHAIN_STEPS, tail_length.numpy())
        if left:
            lanes = where_true(tail_length < 0)
            closed, _, _ = leak.fire_through(tail_u[lanes], tail_gap[lanes],
                                             torch.ones(left, dtype=torch.bool))
            tail_length[lanes] = closed
        run = torch.cat([run, torch.stack([tail[0], tail[1], tail[2], tail_length])], 1)
    return CellSpikes(spike[0], spike[1], run[0], run[1], run[2], run[3])
