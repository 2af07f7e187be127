"""LIF pooling's rounds: snntorch's float32 update at every cell, all regions at once.

Used by :func:`.pooling.lif_spikes` (see its module docstring):
round ``r`` updates the ``r``-th cell of every region that has one. Lanes are regions by
decreasing number of cells, so the lanes of a round are a prefix of the previous round's and
every update is a slice; a round costs a fixed few tensor operations, and there are as many
rounds as the busiest region has cells. On the CPU a compiled loop takes the cells in their
own order instead, region by region (:mod:`evdown_torch.transforms.functional.compiled.lif`,
the same float32 operations, firing chains included; no reordering) unless the eager kernels
are forced; only a cell with a chain longer than ``EXACT_CHAIN_STEPS`` steps, or decaying over
``2 ** LOW_BITS`` steps after one, is this module's round there (on that cell alone).
"""

from __future__ import annotations

import torch
from torch import Tensor

from evdown_torch._tensors import divide, run_index, stable_sort_small, where_true
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.lif.chains import CellSpikes, Leak, Rounds

__all__ = ["membranes_by_rounds", "spikes_and_runs"]


def membranes_by_rounds(
    current: Tensor,
    gap_before: Tensor,
    region_first: Tensor,
    new_region: Tensor,
    cells_per_region: Tensor,
    *,
    rounds: int,
    leak: Leak,
) -> tuple[Tensor, Tensor]:
    """Every neuron's membrane after the update at each cell, and its spikes in the gap before.

    Args:
        current: ``(n, 2)`` float32 input currents of the cells' (OFF, ON) neurons (a state
            cell's current is its membrane), cells sorted by region, then step.
        gap_before: ``(n,)`` int64 empty steps before every cell (after the previous cell of
            its region).
        region_first: ``(R,)`` int64 index of every region's first cell.
        new_region: ``(n,)`` bool, True at every region's first cell (``region_first``).
        cells_per_region: ``(R,)`` int64 number of cells of every region.
        rounds: the largest number of cells of one region.
        leak: the neurons' ``beta``, threshold and reset.

    Returns:
        ``(membrane, chain_before)``: ``(n, 2)`` float32 membranes after each cell's update,
        and ``(n, 2)`` int64 spikes fired in the gap before the cell by a neuron that went on
        firing after the previous cell (reset "subtract"; the first steps of the gap).
    """
    if use_compiled(current):
        return _membranes_cell_by_cell(current, gap_before, new_region, leak)
    device = current.device
    region_index = run_index(new_region)  # region (0 .. R - 1) of every cell
    f32 = torch.float32
    n_cells, n_regions = current.shape[0], region_first.shape[0]
    count_sorted, region_of_lane = stable_sort_small(rounds - cells_per_region, rounds + 1)
    lane_of_region = torch.empty_like(region_of_lane)
    lane_of_region.index_copy_(0, region_of_lane, torch.arange(n_regions, device=device))
    # lanes in round r: the regions with more than r cells
    lanes_per_round = n_regions - torch.searchsorted(
        count_sorted.flip(0).neg_().add_(rounds), torch.arange(rounds, device=device),
        right=True,
    )
    round_start = torch.zeros(rounds + 1, dtype=torch.int64, device=device)
    torch.cumsum(lanes_per_round, 0, out=round_start[1:])
    # position in round order: round start of the cell's rank, plus its region's lane
    slot = torch.arange(n_cells, device=device).sub_(region_first.index_select(0, region_index))
    slot = round_start.index_select(0, slot).add_(lane_of_region.index_select(0, region_index))
    del lane_of_region, region_of_lane, count_sorted
    gap_in_rounds = torch.empty(n_cells, 1, dtype=torch.int64, device=device)
    gap_in_rounds.index_copy_(0, slot, gap_before[:, None])
    current_in_rounds = torch.empty_like(current).index_copy_(0, slot, current)
    # A membrane at or below threshold only decays through a gap: beta ** g, rounded once
    # (exactly snntorch's product for g <= 1); after one step of a firing chain, beta ** (g - 1).
    # Each a function of g alone, not of the cell's place among the call's cells (lif/powers).
    decay_in_rounds = leak.powers.float32(gap_in_rounds)
    decay_after_one = leak.powers.float32((gap_in_rounds - 1).clamp_(min=0))
    silent_in_rounds = gap_in_rounds > 0
    chain_in_rounds = torch.zeros(n_cells, 2, dtype=torch.int64, device=device)

    # The rounds: snntorch.Leaky's float32 update at every cell, in its order. The lanes of
    # round r are the first lanes of round r - 1, so a lane's membrane is read back from there.
    mem_in_rounds = torch.empty(n_cells, 2, dtype=f32, device=device)
    bounds = round_start.tolist()
    mem_in_rounds[: bounds[1]] = current_in_rounds[: bounds[1]]  # from zero: beta * 0 + I
    rounds_in = Rounds(mem_in_rounds, current_in_rounds, decay_in_rounds, decay_after_one,
                        silent_in_rounds, gap_in_rounds, chain_in_rounds, bounds)
    for r in range(1, rounds):
        _round(rounds_in, r, leak)
    # back to cell order
    return mem_in_rounds.index_select(0, slot), chain_in_rounds.index_select(0, slot)


def _membranes_cell_by_cell(
    current: Tensor, gap_before: Tensor, first: Tensor, leak: Leak
) -> tuple[Tensor, Tensor]:
    """:func:`membranes_by_rounds` on the CPU: a compiled loop over the cells in their order.

    The same membranes and chains, bit for bit: each cell's update reads only its region's
    previous cell, so the cells need no reordering into rounds. A cell whose firing chain the
    loop cannot follow is :func:`_round`'s, as a round of one lane (its previous cell, then
    it: rows ``i - 1`` and ``i``, written in place), and the loop goes on after it.
    """
    from evdown_torch.transforms.functional.compiled import lif

    n_cells = current.shape[0]
    gap = gap_before[:, None]
    membrane = torch.empty_like(current)
    decay = leak.powers.float32(gap)
    decay_after_one = leak.powers.float32((gap - 1).clamp_(min=0))
    chain = torch.zeros(n_cells, 2, dtype=torch.int64)
    columns = (membrane, current, decay, decay_after_one, gap, first, chain)
    i = lif.cells_until_chain(*columns, start=0, leak=leak)
    while i < n_cells:  # (i >= 1: a region's first cell has no gap to fire through)
        rows = slice(i - 1, i + 1)
        _round(Rounds(membrane[rows], current[rows], decay[rows], decay_after_one[rows],
                      gap[rows] > 0, gap[rows], chain[rows], [0, 1, 2]), 1, leak)
        i = lif.cells_until_chain(*columns, start=i + 1, leak=leak)
    return membrane, chain


def _round(rounds: Rounds, r: int, leak: Leak) -> None:
    """Round ``r >= 1``: snntorch's update at the ``r``-th cell of every region that has one.

    The compiled loop (:func:`~evdown_torch.transforms.functional.compiled.lif.
    cells_until_chain`) does the same arithmetic, cell by cell.
    """
    beta32, threshold32, reset_mechanism = leak.beta32, leak.threshold32, leak.reset
    bounds = rounds.bounds
    a, b = bounds[r], bounds[r + 1]
    u = rounds.membrane[bounds[r - 1] : bounds[r - 1] + b - a]
    fired = u > threshold32  # the reset signal of the next step, unless a gap follows
    w = u * rounds.decay[a:b]
    reset = None  # R = 1 where a neuron fired in the step just before this cell
    if reset_mechanism == "zero":  # reset at the next step, then silent: W = 0 either way
        w.masked_fill_(fired, 0.0)
    elif reset_mechanism == "subtract" and bool(fired.any()):
        silent = rounds.silent[a:b]
        moving = fired & silent  # fired, then empty steps: one step of the chain, U - theta
        chain = beta32 * u - threshold32  # (+ a zero current: exact)
        w = torch.where(moving, chain * rounds.decay_after_one[a:b], w)
        fired &= ~silent
        longer = moving & (chain > threshold32)
        if bool(longer.any()):  # still firing after one empty step: the chain goes on
            longer = where_true(longer.view(-1))  # (neurons of lanes, flattened)
            lane = divide(longer, 2)
            count, chained, still = leak.fire_through(
                u.reshape(-1).index_select(0, longer),
                rounds.gap.index_select(0, lane.add_(a)).squeeze(1),
                torch.ones(longer.shape, dtype=torch.bool, device=u.device))
            w.view(-1).index_copy_(0, longer, chained)
            fired.view(-1).index_copy_(0, longer, still)
            rounds.chain[a:b].view(-1).index_copy_(0, longer, count)
        reset = fired
    out = torch.mul(beta32, w, out=rounds.membrane[a:b])
    out += rounds.current[a:b]
    if reset is not None:
        torch.where(reset, out - threshold32, out, out=out)


def spikes_and_runs(
    membrane: Tensor,
    chain_before: Tensor,
    cell_step: Tensor,
    gap_before: Tensor,
    gap_after: Tensor,
    region_last: Tensor,
    *,
    leak: Leak,
) -> CellSpikes:
    """The rounds' spikes (:class:`~.chains.CellSpikes`).

    Those at the cells, and the runs of spikes of neurons that go on firing through the
    silent steps after a cell. On the CPU a compiled loop finds them
    (:func:`evdown_torch.transforms.functional.compiled.lif.spikes_and_runs`; the tails'
    lengths stay :meth:`~.chains.Leak.fire_through`'s): the same spikes, in the same order.
    """
    if use_compiled(membrane):
        from evdown_torch.transforms.functional.compiled import lif

        return lif.spikes_and_runs(membrane, chain_before, cell_step, gap_before, gap_after,
                                   region_last, leak=leak)
    fired = membrane > leak.threshold32
    spike_cell, spike_polarity = fired.nonzero(as_tuple=True)  # cell-major
    # Runs found in the rounds (reset "subtract", gaps between cells) or here (the tail after a
    # region's last cell; every gap with reset "none", whose membrane does not depend on them).
    run_cell, run_polarity = (chain_before > 0).nonzero(as_tuple=True)
    run_length = chain_before[run_cell, run_polarity]
    run_start = cell_step[run_cell] - gap_before[run_cell]  # run_cell: the region, for below
    if leak.reset != "zero":
        if leak.reset == "subtract":  # only the tails: the rounds found the others
            candidate = fired.index_select(0, region_last)
            candidate &= (gap_after.index_select(0, region_last) > 0)[:, None]
            tail_cell, tail_polarity = candidate.nonzero(as_tuple=True)
            tail_cell = region_last[tail_cell]
        else:
            candidate = fired & (gap_after > 0)[:, None]
            tail_cell, tail_polarity = candidate.nonzero(as_tuple=True)
        tail_gap = gap_after.index_select(0, tail_cell)
        tail_length, _, _ = leak.fire_through(
            membrane[tail_cell, tail_polarity], tail_gap, tail_gap > 0
        )
        run_cell = torch.cat([run_cell, tail_cell])
        run_polarity = torch.cat([run_polarity, tail_polarity])
        run_length = torch.cat([run_length, tail_length])
        run_start = torch.cat([run_start, cell_step[tail_cell] + 1])
    return CellSpikes(spike_cell, spike_polarity, run_cell, run_polarity, run_start, run_length)

