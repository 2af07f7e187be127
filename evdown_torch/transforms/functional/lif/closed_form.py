"""LIF pooling's spikes without rounds: the membranes between firings in closed form, certified.

The rounds of :func:`~evdown_torch.transforms.functional.lif.pooling.lif_spikes` update the ``k``-th
cell of every region at once, so a call costs a fixed few tensor operations per active step of
its busiest region: about 160 to 300 rounds for a 0.3 s N-MNIST recording at ``dt`` = 1 ms,
most of a small call's time. This module computes the same spikes in far fewer passes, for
calls whose cells fit a small padded ``(region, rank)`` table:

- **Between firings the membrane is linear.** Given which cells fire, a neuron's membrane at
  its ``k``-th cell is ``v_k = beta ** (s_k - s_{k-1}) * v_{k-1} + B_k`` (``s``: the cells'
  steps), with ``B_k`` the cell's input, less ``theta * beta ** gap`` after a firing (reset
  "subtract"; more for a neuron that fires on into empty steps), or a restart ``v_k = I_k``
  after one (reset "zero"). Scaled by ``beta ** -(s_k - s_0)`` this is a cumulative sum along
  the region's row: one ``cumsum`` gives every membrane of every neuron, in float64.
- **Firings by binary search.** Scaled, a neuron fires at the first cell where the running
  maximum of its input-only trajectory exceeds the resets it has paid so far; each pass finds
  the next firing of every neuron at once (:func:`_greedy_firings`), so there are as many
  passes as the busiest neuron fires (37 for the N-MNIST sample at factor 4, against 157
  rounds), each a few operations.
- **Certified.** The rounds' arithmetic is snntorch's float32 update, rounded at every step;
  this module's float64 membranes are close to the exact real ones. A second ``cumsum`` bounds
  the float32 rounding that the rounds accumulate (a few units in the last place per update,
  decaying with the membrane), so that every decision (a membrane above threshold or not, a
  firing chain through empty steps going on or not) whose float64 value lies farther from
  the threshold than the bound is the rounds' own. When any decision lies within the bound
  (a membrane exactly on the threshold, for example), or the call is one this module leaves
  to the rounds (``beta = 0``, a span whose scaling would overflow float64, gaps of ``2 ** 24``
  steps or more), it returns ``None`` and the rounds compute the call: the spikes are always
  the rounds' spikes.

Rounding bounds, derived (``eps32 = 2**-24``, ``eps64 = 2**-53``, ``KAPPA = 16 eps32``):

1. *One update at a cell.* snntorch's update ``v_k = beta**gap * v_{k-1} + I_k - reset`` is at
   most six float32 roundings (the power, three products and sums, the reset), each within
   ``eps32`` of the size it rounds, so within ``12 eps32 <= KAPPA`` times the sum of the sizes
   ``beta**gap |v_{k-1}| + |I_k| + |v_k| + theta``; the error carried from ``v_{k-1}`` is
   multiplied by the float32 ``beta**gap``, i.e. by ``beta**gap (1 + 8 eps32)`` at most.
2. *Along a row.* Scaling by ``beta**-(s_k - s_0)`` turns the recursion into a sum: the
   scaled error ``E_k`` is at most ``(1 + 8 eps32)**width`` times the sum over ``i <= k`` of
   ``KAPPA (2 |Y_i| + (|I_i| + theta) scale_i)`` (each membrane counted as the size before
   and after its update). ``growth`` adds 1 % for the float64 cumsum of that sum, and
   ``float64_error = 16 eps64 (width + lam * widest + 16)`` the float64 error of ``Y`` itself
   (a cumsum of ``width`` terms, scales ``exp(lam * offset)`` of relative error about
   ``lam * offset`` units). A decision is certain when its margin exceeds that sum.
3. *A firing chain before a cell* (reset "subtract", between cells) is at most
   :data:`~.chains.EXACT_CHAIN_STEPS` = 8 float32 steps, each of two roundings of sizes
   below ``|v| + theta`` (the membrane falls along a chain), then a float64 closed form: at
   most ``16 KAPPA (|v| + theta)`` in all, added at the next cell.
4. *Where a chain stops.* The chain ``j`` steps after a membrane ``u`` with error bound
   ``error`` is ``chain(u, j)`` (:class:`~.chains.Leak`); the rounds' float32 value lies
   within ``beta**j error`` (the carried error decays) plus ``2 eps32 (u + theta)`` per
   float32 step, of which there are at most 8 (then the closed form adds float64 error only):
   ``2 min(j, 8) eps32 (u + theta)``. The code uses ``KAPPA (2 min(j, 9) + 4) (u + theta)``,
   which bounds that by a factor of 16 or more (one more step, and ``4 KAPPA`` for rounding
   ``u`` to float32 at the chain's start), plus ``1e-12 (u + A + j theta)`` for the float64
   evaluation of ``(u + A) beta**j - A`` (``A = theta / (1 - beta)``: a few ``eps64`` of
   those sizes, covered a thousandfold). The test of the first empty step for all chains at
   once is the case ``j = 1`` with ``6 KAPPA >= (2 + 4) KAPPA``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evdown_torch._tensors import where_true
from evdown_torch.transforms.functional.lif.chains import CellSpikes, Leak

__all__ = ["MAX_TABLE", "MIN_ROUNDS", "certain_spikes"]

#: Passes of the greedy search between two checks for a neuron still above threshold.
_BLOCK = 16

#: Largest padded table (regions x largest number of cells of one region) computed in closed
#: form; larger calls (long streams, big batches) go through the rounds, whose fixed cost per
#: round is then small against their work.
MAX_TABLE = 1 << 17

#: Fewest rounds worth replacing (below this the rounds cost less than the passes).
MIN_ROUNDS = 12

_EPS32 = 2.0**-24  # unit roundoff of float32
_EPS64 = 2.0**-53
#: Bound on the relative float32 rounding of one cell's update (a power, three products and
#: sums, a reset: at most about six roundings, each at most one unit roundoff, doubled).
_KAPPA = 16 * _EPS32
#: Largest ``ln(beta) * (s_k - s_0)`` scaled in float64 (``exp(600)`` is finite).
_MAX_EXPONENT = 600.0


def certain_spikes(
    cell_step: Tensor,
    current: Tensor,
    region_first: Tensor,
    region_index: Tensor,
    cells_per_region: Tensor,
    gap_after: Tensor,
    *,
    rounds: int,
    leak: Leak,
) -> CellSpikes | None:
    """The spikes of the rounds, in closed form, or ``None`` where they are not certain.

    Args:
        cell_step: ``(n,)`` int64 steps of the cells, sorted by region, then step.
        current: ``(n, 2)`` float32 input currents of the cells' (OFF, ON) neurons (a state
            cell's current is its membrane).
        region_first: ``(R,)`` int64 index of every region's first cell.
        region_index: ``(n,)`` int64 region (row, ``0 .. R - 1``) of every cell.
        cells_per_region: ``(R,)`` int64 number of cells of every region.
        gap_after: ``(n,)`` int64 empty steps after every cell (to the next cell of its
            region, or to the last step after its last cell).
        rounds: the largest number of cells of one region.
        leak: the neurons' ``beta``, threshold and reset.

    Returns:
        The :class:`~.chains.CellSpikes`: the neurons whose membrane exceeds the
        threshold after the update at a cell, and the runs of spikes a neuron fires through
        the empty steps after a cell (``run_length`` spikes from step ``run_start``);
        ``None`` when a decision lies within float32 rounding of the threshold or the call is
        left to the rounds.
    """
    n_regions, width = region_first.shape[0], rounds
    beta, theta, reset = leak.beta, leak.threshold, leak.reset
    if beta == 0.0 or n_regions * width > MAX_TABLE:
        return None
    device = cell_step.device
    f64 = torch.float64
    n = cell_step.shape[0]
    base = region_first.index_select(0, region_index)  # the first cell of every cell's row
    pos = torch.arange(n, device=device).sub_(base).add_(region_index, alpha=width)  # in table
    offset = cell_step - cell_step.index_select(0, base)
    widest, longest_gap = torch.stack([offset.max(), gap_after.max()]).tolist()
    lam = -math.log(beta)  # 0 for beta = 1
    if lam * widest > _MAX_EXPONENT or longest_gap >= 1 << 24:
        return None  # scaling would overflow; the rounds' float32 powers round such gaps

    # The (R, width) scale beta ** -(s_k - s_0) (1 on pads, after every cell of their row: no
    # effect on the cells) and the (2, R, width) scaled inputs (of exact float64 copies).
    cell_scale = offset.to(f64).mul_(lam).exp_()
    scale = torch.ones(n_regions * width, dtype=f64, device=device)
    scale.index_copy_(0, pos, cell_scale)
    scale = scale.view(n_regions, width)
    invalid = torch.arange(width, device=device) >= cells_per_region[:, None]  # the pads
    inputs = torch.zeros(2, n_regions * width, dtype=f64, device=device)
    inputs.index_copy_(1, pos, current.t().to(f64).mul_(cell_scale))
    inputs = inputs.view(2, n_regions, width)
    level = scale * theta  # the threshold, scaled
    summed = torch.cumsum(inputs, -1)

    # The firings, then every membrane, scaled (Y_k = v_k * scale_k), checked against them.
    gain = between = None  # reset "subtract": a firing's reset, scaled; empty steps to the
    if reset == "subtract":  # next cell of the row (0 after the last)
        gain = level * (1.0 / beta)
        between = torch.zeros(n_regions * width, dtype=torch.int64, device=device)
        between[pos] = gap_after
        between = between.view(n_regions, width)
        between.scatter_(1, cells_per_region[:, None] - 1, 0)

    def membranes(fired: Tensor, chains: Tensor | None) -> Tensor:
        """Every membrane given the firings, scaled."""
        if gain is not None:  # reset "subtract" (gain: its reset, scaled): a firing at i
            share = fired * gain  # subtracts theta at steps s_i + 1 .. s_i + 1 + m
            if chains is not None:  # m spikes in the empty steps after the cell
                at = chains.nonzero(as_tuple=True)
                share[at] *= _geometric(chains[at], beta)
            return (summed - torch.cumsum(share, -1)).add_(share)
        if reset == "zero":  # the membrane restarts after a firing: the sum from there on
            before = torch.zeros_like(fired)
            before[..., 1:] = fired[..., :-1]
            restart = torch.where(before, torch.arange(width, device=device), 0).cummax(-1).values
            earlier = summed.gather(-1, (restart - 1).clamp_(min=0))
            return summed - earlier.masked_fill_(restart == 0, 0.0)  # 0: from the row's start
        return summed

    fired, chains = _greedy_firings(summed, level, gain, invalid, scale, between, leak=leak)
    scaled = membranes(fired, chains)

    # The float32 rounding the rounds accumulate: at each update at most KAPPA times the sizes
    # it involves (beta ** gap * |v_{k-1}|, |I_k|, |v_k|, theta), and the earlier error scaled
    # by beta ** gap * (1 + 8 eps). Scaled, the sum of the sizes up to k is at most
    # 2 * sum |Y| + sum (|I| + theta) * scale (ignoring the restarts of reset "zero" only
    # makes it larger); float64's own error is a small share of the latter. A firing chain
    # through the empty steps before a cell adds at most 16 KAPPA (|v| + theta) there.
    local = inputs.abs_().add_(level)  # (|I| + theta) * scale: inputs is not needed after this
    if chains is not None:  # at the cell after each chain
        polarity, row, rank = chains.nonzero(as_tuple=True)
        ratio = scale[row, rank + 1] / scale[row, rank]
        local[polarity, row, rank + 1] += (scaled[polarity, row, rank].abs() * ratio
                                           + level[row, rank + 1]) * 16
    growth = (1.0 + 8 * _EPS32) ** width * 1.01
    float64_error = 16 * _EPS64 * (width + lam * widest + 16)
    # one cumsum of both sums, weighted (its rounding is far inside the 1.01 of growth)
    local.mul_(_KAPPA * growth + float64_error).add_(scaled.abs(), alpha=2 * _KAPPA * growth)
    bound = torch.cumsum(local, -1)
    # Certain: every membrane on the side of the threshold that the firings say (else a
    # decision within float64 rounding, or the greedy search wrong) by more than the bound.
    margin = scaled - level
    margin = torch.where(fired, margin, margin.neg())
    if not bool((margin > bound).logical_or_(invalid).all()):
        return None

    polarity, row, rank = fired.nonzero(as_tuple=True)
    cell = region_first.index_select(0, row).add_(rank)
    empty = torch.empty(0, dtype=torch.int64, device=device)
    if reset == "zero":
        return CellSpikes(cell, polarity, empty, empty, empty, empty)
    chain = gap_after.index_select(0, cell) > 0  # fired, then empty steps
    if not bool(chain.any()):
        return CellSpikes(cell, polarity, empty, empty, empty, empty)
    which = where_true(chain)
    chain_cell, chain_polarity = cell.index_select(0, which), polarity.index_select(0, which)
    at = (chain_polarity, row.index_select(0, which), rank.index_select(0, which))
    if reset == "none" and beta == 1.0:  # the membrane stays: fires at every empty step
        return CellSpikes(cell, polarity, chain_cell, chain_polarity, cell_step[chain_cell] + 1,
                          gap_after.index_select(0, chain_cell))
    # The neuron fires on while the chain (membrane decaying, less theta at every step with
    # reset "subtract") stays above threshold. Most stop at once: certain where the first
    # empty step's membrane, beta * u (- theta), lies below threshold by more than its bound,
    # beta * error + 6 KAPPA (u + theta) + 1e-12 (u + A + theta) (u: the membrane, error:
    # its bound). First for all at once, scaled (Y = u * scale, bound = error * scale; the
    # 1e-12 covers float64's rounding of either form), then unscaled for the others.
    offset_a = leak.offset if beta < 1.0 else 0.0
    below = 2.0 if reset == "subtract" else 1.0  # beta * u - theta < theta, or beta * u < theta
    lead = (below - 6 * _KAPPA - 1e-12) * theta - 1e-12 * offset_a
    ahead = torch.mul(scaled[at], beta + 6 * _KAPPA + 1e-12).add_(bound[at], alpha=beta)
    if chains is None and bool((ahead < scale[at[1:]] * lead).all()):
        return CellSpikes(cell, polarity, empty, empty, empty, empty)
    gap = gap_after.index_select(0, chain_cell)
    unscale = 1.0 / scale[at[1:]]
    u = scaled[at] * unscale  # the membranes, and their bounds
    error = bound[at] * unscale
    counted = chains[at] if chains is not None else torch.zeros_like(gap)
    inner = between[at[1:]] > 0 if between is not None else None  # gaps between cells
    first = beta * u - theta if reset == "subtract" else beta * u
    quiet = first < theta - (beta * error + 6 * _KAPPA * (u + theta)
                             + 1e-12 * (u + offset_a + theta))
    if bool(quiet.all()):
        if bool((counted == 0).all()):
            return CellSpikes(cell, polarity, empty, empty, empty, empty)
        return None  # the greedy pass counted a chain that is not there
    if bool((counted[quiet] != 0).any()):
        return None
    loud = ~quiet
    chain_cell, chain_polarity, gap, counted = (
        chain_cell[loud], chain_polarity[loud], gap[loud], counted[loud])
    u, error = u[loud], error[loud]
    # The others, in closed form: certain where both ends of the run are.
    run = torch.minimum(leak.run(u), gap.to(f64))
    if inner is not None and not bool((run == counted)[inner[loud]].all()):
        return None  # the chains between cells are those the greedy pass counted
    last = run.clamp(min=1.0)  # the last step that fires (checked where run >= 1)
    after = run + 1.0  # the first that does not (checked where run < gap)
    margins = [
        torch.pow(beta, j) * error + _KAPPA * (2 * j.clamp(max=9.0) + 4) * (u + theta)
        + 1e-12 * (u + offset_a + j * theta)
        for j in (last, after)
    ]
    ok = (run < 1.0) | (leak.chain(u, last) - theta > margins[0])
    ok &= (run >= gap.to(f64)) | (theta - leak.chain(u, after) > margins[1])
    if not bool(ok.all()):
        return None
    length = run.to(torch.int64)
    keep = length > 0
    chain_cell, chain_polarity, length = chain_cell[keep], chain_polarity[keep], length[keep]
    return CellSpikes(cell, polarity, chain_cell, chain_polarity, cell_step[chain_cell] + 1,
                      length)


def _geometric(count: Tensor, beta: float) -> Tensor:
    """``sum_{t = 0}^{m} beta ** -t`` for counts ``m``.

    A firing and ``m`` chained spikes, each subtracting theta one step later, scaled to the
    firing's own reset.
    """
    m = count.to(torch.float64)
    if beta == 1.0:
        return m + 1.0
    return torch.pow(1.0 / beta, m + 1.0).sub_(1.0).div_(1.0 / beta - 1.0)


def _greedy_firings(
    summed: Tensor,
    level: Tensor,
    gain: Tensor | None,
    invalid: Tensor,
    scale: Tensor,
    between: Tensor | None,
    *,
    leak: Leak,
) -> tuple[Tensor, Tensor | None]:
    """Every neuron's firings, one firing of every neuron per pass, by binary search.

    Scaled by ``beta ** -(s_k - s_0)``, a neuron's membrane at cell ``k`` exceeds the
    threshold when ``X_k = S_k - theta * scale_k`` (``S``: its cumulative scaled input,
    ``summed``; ``theta * scale``: ``level``) exceeds ``D``, the scaled resets of its
    firings so far (reset "subtract": ``D`` grows by ``theta * scale_i / beta`` at a firing
    at cell ``i``, ``gain``; reset "zero": the membrane restarts after it, ``D = S_i``).
    After a firing at ``i`` the next one is the first cell after ``i`` whose ``X`` exceeds
    ``D``: the first cell whose running maximum of ``X`` exceeds ``D`` (a binary search),
    once the ``X`` up to ``i`` are masked out where one of them exceeds ``D``. That happens
    where the neuron is still above threshold after its reset: with reset "subtract" and
    empty steps after the cell (``between``), it fires on through them, ``m`` more spikes
    (counted in closed form) whose resets add to ``D``. In exact arithmetic these are the
    recurrence's firings; the caller checks them against the float64 membranes.

    Args:
        summed: ``(2, R, width)`` float64 ``S``.
        level: ``(R, width)`` float64 ``theta * scale``.
        gain: ``(R, width)`` float64 ``theta * scale / beta`` (reset "subtract"; ``None``
            otherwise).
        invalid: ``(R, width)`` bool, the pads after every row's cells.
        scale: ``(R, width)`` float64 ``beta ** -(s_k - s_0)``.
        between: ``(R, width)`` int64 empty steps to the row's next cell (reset
            "subtract"; ``None`` otherwise).
        leak: the neurons' ``beta``, threshold and reset.

    Returns:
        ``(fired, chains)``: ``(2, R, width)`` bool, the firings (none on pads), and int64
        spikes chained into the empty steps after each firing (``None`` where there are
        none).
    """
    lead, width = summed.shape[:-1], summed.shape[-1]
    rise = torch.sub(summed, level).masked_fill_(invalid, -math.inf)
    if leak.reset == "none":
        return rise > 0, None
    # What a firing adds to D ("subtract") or sets it to ("zero"); +inf after the last column
    # (a search that finds nothing returns ``width``: D becomes inf, the neuron is done).
    if gain is not None:
        step = torch.nn.functional.pad(gain, (0, 1), value=math.inf).expand(*lead, width + 1)
    else:
        step = torch.nn.functional.pad(summed, (0, 1), value=math.inf)
    peak = torch.cummax(rise, -1).values
    debt = torch.zeros(*lead, 1, dtype=summed.dtype, device=summed.device)
    # The last firing before the block (-1: none).
    last = torch.full_like(debt, -1, dtype=torch.int64)
    chains: list[tuple[Tensor, Tensor, Tensor, Tensor]] = []  # (polarity, row, column, count)
    blocks = []
    for _ in range(2 * width + 2):  # a block finds a firing of, or masks, every neuron not done
        # _BLOCK passes unchecked, then a look back: a neuron that found its last firing
        # again (still above threshold after it) keeps its firings up to there and searches
        # after it from then on.
        found, debts = [], [debt]
        for _ in range(_BLOCK):
            at = torch.searchsorted(peak, debt, right=True)  # width: none left
            debt = step.gather(-1, at).add_(debt) if gain is not None else step.gather(-1, at)
            found.append(at)
            debts.append(debt)
        block = torch.cat(found, -1)
        before = torch.cat([last, block[..., :-1]], -1)
        behind = (block <= before).logical_and_(block < width)
        last = found[-1]  # increasing along a block, up to width (none left)
        blocks.append(block)
        if bool(behind.any()):
            _look_back(block, before, behind, debts, debt, last, rise, peak, summed, step, scale,
                       between, chains, leak)
        elif bool(last.eq(width).all()):
            break
    fired = torch.zeros(*lead, width + 1, dtype=torch.bool, device=summed.device)
    fired.scatter_(-1, torch.cat(blocks, -1), True)
    if not chains:
        return fired[..., :width], None
    table = torch.zeros(summed.shape, dtype=torch.int64, device=summed.device)
    polarity, row, column, count = (torch.cat(part) for part in zip(*chains, strict=True))
    table[polarity, row, column] = count
    return fired[..., :width], table


def _look_back(
    block: Tensor,
    before: Tensor,
    behind: Tensor,
    debts: list[Tensor],
    debt: Tensor,
    last: Tensor,
    rise: Tensor,
    peak: Tensor,
    summed: Tensor,
    step: Tensor,
    scale: Tensor,
    between: Tensor | None,
    chains: list[tuple[Tensor, Tensor, Tensor, Tensor]],
    leak: Leak,
) -> None:
    """A block's neurons still above threshold after a firing, made to fire on.

    ``behind``: a pass found that firing, or an earlier cell, again. Their later passes are
    undone, their chained spikes counted (reset "subtract") and their search masked up to
    the firing. Everything is updated in place: ``block``, ``debt`` (their D after that
    firing), ``last`` (that firing), ``rise`` and ``peak``; the chains with spikes join
    ``chains``.
    """
    n_regions, width = rise.shape[-2:]
    passes = block.shape[-1]
    undone = behind.cumsum(-1) > 0  # the passes from the first gone wrong on
    block.masked_fill_(undone, width)
    kept = undone.logical_not_().sum(-1, keepdim=True)  # passes kept, < passes where wrong
    wrong = kept < passes
    first = kept.clamp_(max=passes - 1)
    fired_at = before.gather(-1, first)  # the firing it is still above after
    debt.copy_(torch.where(wrong, torch.cat(debts, -1).gather(-1, first), debt))
    last.copy_(torch.where(wrong, fired_at, last))
    lanes = where_true(wrong.view(-1))  # the neurons gone wrong
    fired_at = fired_at.view(-1).index_select(0, lanes)
    if between is not None:  # reset "subtract": chained spikes, their resets
        onward = between[lanes.remainder(n_regions), fired_at] > 0
        if bool(onward.any()):
            _chain(lanes[onward], fired_at[onward], debt, chains, summed, step, scale, between,
                   leak)
    # search after the firing from then on
    after = rise.view(-1, width).index_select(0, lanes)
    after.masked_fill_(torch.arange(width, device=lanes.device) <= fired_at[:, None], -math.inf)
    rise.view(-1, width).index_copy_(0, lanes, after)
    peak.view(-1, width).index_copy_(0, lanes, torch.cummax(after, -1).values)


def _chain(
    lanes: Tensor,
    column: Tensor,
    debt: Tensor,
    chains: list[tuple[Tensor, Tensor, Tensor, Tensor]],
    summed: Tensor,
    step: Tensor,
    scale: Tensor,
    between: Tensor,
    leak: Leak,
) -> None:
    """Reset "subtract": the spikes that neurons chain into the empty steps after a firing.

    The neurons ``lanes`` (``polarity * R + row``) are still above threshold after their
    firing at ``column``; their resets join ``D`` (``debt``, in place), the chains with
    spikes join ``chains``.
    """
    n_regions = scale.shape[0]
    polarity, row = lanes.div(n_regions, rounding_mode="floor"), lanes.remainder(n_regions)
    before = debt.view(-1)[lanes]  # D after this firing's own reset
    d = step[polarity, row, column]
    u = (summed[polarity, row, column] - (before - d)) / scale[row, column]
    # Most chains stop at once (the first empty step's membrane below threshold): no spikes,
    # nothing to add (leak.run gives 0 exactly where this is so).
    if not bool((leak.chain(u, torch.ones_like(u)) > leak.threshold).any()):
        return
    gap = between[row, column]
    count = torch.minimum(leak.run(u), gap.to(u.dtype)).to(torch.int64)
    debt.view(-1).index_copy_(0, lanes, before + d * (_geometric(count, leak.beta) - 1.0))
    some = count > 0
    chains.append((polarity[some], row[some], column[some], count[some]))
