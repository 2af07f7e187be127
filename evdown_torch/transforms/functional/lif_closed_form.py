"""LIF pooling's spikes without rounds: the membranes between firings in closed form, certified.

The rounds of :func:`~evdown_torch.transforms.functional.lif.lif_spikes` update the ``k``-th
cell of every region at once, so a call costs a fixed few tensor operations per active step of
its busiest region: about 300 rounds for a 0.3 s N-MNIST recording at ``dt`` = 1 ms, most of a
small call's time. This module computes the same spikes with a number of passes that does not
grow with the steps, for calls whose cells fit a small padded ``(region, rank)`` table:

- **Between firings the membrane is linear.** Given which cells fire, a neuron's membrane at
  its ``k``-th cell is ``v_k = beta ** (s_k - s_{k-1}) * v_{k-1} + B_k`` (``s``: the cells'
  steps), with ``B_k`` the cell's input, minus ``theta * beta ** gap`` after a firing (reset
  "subtract"), or a restart ``v_k = I_k`` after one (reset "zero"). Scaled by
  ``beta ** -(s_k - s_0)`` this is a cumulative sum along the region's row: one ``cumsum``
  gives every membrane of every neuron, in float64.
- **Firings by fixed point.** The firings are found by iterating ``f <- (v(f) > theta)`` from
  "none fire": where the firings before a cell are right its membrane is right, so each pass
  settles at least the next cell of every neuron, and in practice a handful of passes settle
  all of them (a membrane forgets a wrong reset within a few time constants).
- **Certified.** The kernel's arithmetic is snntorch's float32 update, rounded at every step;
  this module's float64 membranes are close to the exact real ones. A second ``cumsum`` bounds
  the float32 rounding that the kernel accumulates (a few units in the last place per update,
  decaying with the membrane), so that every decision (a membrane above threshold or not, a
  firing chain through empty steps going on or not) whose float64 value lies farther from
  the threshold than the bound is the kernel's own. When any decision lies within the bound,
  or the call has a case this module leaves to the rounds (a reset "subtract" neuron that
  keeps firing into empty steps, ``beta = 0``, a span whose scaling would overflow), it
  returns ``None`` and the rounds compute the call: the spikes are always the rounds' spikes.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evdown_torch.transforms.functional.lif_chains import Leak

__all__ = ["MAX_TABLE", "MIN_ROUNDS", "certain_spikes"]

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
    gap_after: Tensor,
    *,
    rounds: int,
    leak: Leak,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None:
    """The spikes of the rounds, in closed form, or ``None`` where they are not certain.

    Args:
        cell_step: ``(n,)`` int64 steps of the cells, sorted by region, then step.
        current: ``(n, 2)`` float32 input currents of the cells' (OFF, ON) neurons.
        region_first: ``(R,)`` int64 index of every region's first cell.
        region_index: ``(n,)`` int64 region (row, ``0 .. R - 1``) of every cell.
        gap_after: ``(n,)`` int64 empty steps after every cell (to the next cell of its
            region, or to the last step after its last cell).
        rounds: the largest number of cells of one region.
        leak: the neurons' ``beta``, threshold and reset.

    Returns:
        ``(fired, run_cell, run_polarity, run_start, run_length)``: ``(n, 2)`` bool, the
        neurons whose membrane exceeds the threshold after the update at the cell, and the
        runs of spikes a neuron fires through the empty steps after a cell (reset "none":
        ``run_length`` spikes from step ``run_start``); ``None`` when a decision is within
        float32 rounding of the threshold or the call is left to the rounds.
    """
    n_regions = region_first.shape[0]
    beta, theta = leak.beta, leak.threshold
    if beta == 0.0 or n_regions * rounds > MAX_TABLE or rounds > 1 << 14:
        return None
    if int(gap_after.max()) >= 1 << 24:  # the rounds' float32 powers round such gaps
        return None
    device = cell_step.device
    f64 = torch.float64
    n = cell_step.shape[0]
    width = rounds
    col = torch.arange(n, device=device) - region_first.index_select(0, region_index)
    pos = region_index * width + col
    first_step = cell_step.index_select(0, region_first)
    offset = cell_step - first_step.index_select(0, region_index)  # s_k - s_0, from 0
    lam = -math.log(beta)  # 0 for beta = 1
    if lam * float(offset.max()) > _MAX_EXPONENT:
        return None

    def table(values: Tensor, fill: float | Tensor = 0.0) -> Tensor:
        """``(..., n)`` cell values into the ``(..., R, width)`` table (pads: ``fill``)."""
        lead = values.shape[:-1]
        out = torch.empty((*lead, n_regions * width), dtype=values.dtype, device=device)
        if isinstance(fill, Tensor):
            out.copy_(fill.reshape(*lead, n_regions * width) if fill.dim() > 1 else fill)
        else:
            out.fill_(fill)
        out[..., pos] = values
        return out.view(*lead, n_regions, width)

    valid = table(torch.ones(n, dtype=torch.bool, device=device), False)
    # Pads repeat their row's last offset: no scaling overflow, no effect on the cells.
    last_offset = torch.empty(n_regions, dtype=torch.int64, device=device)
    last_offset.index_copy_(0, region_index, offset)  # in order: each row's last cell wins
    pad_offset = last_offset[:, None].expand(n_regions, width).reshape(-1)
    dist = table(offset.to(f64), pad_offset.to(f64))  # (R, width)
    scale = torch.exp(dist * lam)
    unscale = torch.exp(dist * -lam)
    inputs = table(current.t().to(f64))  # (2, R, width), exact copies of the float32 currents
    # Per cell: the decay from the previous cell, beta ** (s_k - s_{k-1}) (0 at a row start),
    # and the reset's share after a firing, theta * beta ** gap.
    step_gap = torch.zeros_like(dist)
    torch.sub(dist[:, 1:], dist[:, :-1], out=step_gap[:, 1:])
    decay = torch.exp(step_gap * -lam)
    decay[:, 0] = 0.0
    reset_share = torch.exp((step_gap - 1.0).clamp_(min=0.0) * -lam).mul_(theta)
    columns = torch.arange(width, device=device)
    reset = leak.reset

    def membranes(fired: Tensor) -> tuple[Tensor, Tensor | None]:
        """Every membrane given the firings, and the row restarts (reset "zero")."""
        before = torch.zeros_like(fired)
        before[..., 1:] = fired[..., :-1]
        if reset == "subtract":
            drive = inputs - before * reset_share
        else:
            drive = inputs
        summed = torch.cumsum(drive * scale, -1)
        if reset != "zero":
            return summed * unscale, None
        restart = torch.where(before, columns, 0).cummax(-1).values
        earlier = torch.where(restart > 0, summed.gather(-1, (restart - 1).clamp_(min=0)), 0.0)
        return (summed - earlier) * unscale, restart

    fired = _greedy_firings(inputs, scale, theta=theta, beta=beta, reset=reset) & valid
    v, restart = membranes(fired)
    if not torch.equal((v > theta) & valid, fired):  # a decision within float64 rounding
        return None

    # The float32 rounding the rounds accumulate, decaying as the membrane does; pads add
    # nothing. With reset "zero" a restart's update is beta * 0 + I, exact.
    previous = torch.zeros_like(v)
    previous[..., 1:] = v[..., :-1]
    local = (decay * previous.abs()).add_(inputs.abs()).add_(v.abs()).add_(theta)
    local.mul_(_KAPPA)
    local[..., 0] = 0.0
    local.masked_fill_(~valid, 0.0)
    summed = torch.cumsum(local * scale, -1)
    if restart is not None:
        summed -= torch.where(restart > 0, summed.gather(-1, (restart - 1).clamp_(min=0)), 0.0)
    rounding = summed * unscale
    # Each update also scales the earlier error by at most (1 + 8 eps): compounded here.
    rounding *= (1.0 + 8 * _EPS32) ** width * 1.01
    # float64's own error: cumulative sums of scaled terms over a row, relative to their
    # magnitude (the unrestarted envelope of every input).
    envelope = torch.cumsum((inputs.abs() + theta) * scale, -1).mul_(unscale)
    rounding += envelope * (16 * _EPS64 * (width + lam * float(offset.max()) + 16))
    if not bool(((v - theta).abs() > rounding).logical_or_(~valid).all()):
        return None

    fired_cells = fired.flatten(1)[:, pos].t()  # (n, 2), cell order
    v_cells = v.flatten(1)[:, pos].t()
    bound_cells = rounding.flatten(1)[:, pos].t()
    chain = fired_cells & (gap_after > 0)[:, None]  # fired, then empty steps
    empty = torch.empty(0, dtype=torch.int64, device=device)
    if reset == "zero" or not bool(chain.any()):
        return fired_cells, empty, empty, empty, empty
    chain_cell, chain_polarity = chain.nonzero(as_tuple=True)
    u = v_cells[chain_cell, chain_polarity]
    bound = bound_cells[chain_cell, chain_polarity]
    if reset == "subtract":  # the first empty step, U - theta after the decay, must not fire
        first = beta * u - theta
        if not bool((first < theta - (beta * bound + _KAPPA * (beta * u.abs() + theta))).all()):
            return None
        return fired_cells, empty, empty, empty, empty
    # Reset "none": the membrane only decays, beta ** j * U; the neuron fires while it stays
    # above threshold (every step for beta = 1), certain where both ends of the run are.
    gap = gap_after.index_select(0, chain_cell)
    if beta == 1.0:
        return fired_cells, chain_cell, chain_polarity, cell_step[chain_cell] + 1, gap
    run = torch.minimum(leak.run(u), gap.to(f64))
    last = run.clamp(min=1.0)  # the last step that fires (checked where run >= 1)
    after = run + 1.0  # the first that does not (checked where run < gap)
    margin_last = torch.pow(beta, last) * (bound + _KAPPA * (last.clamp(max=8.0) + 2) * u.abs())
    margin_after = torch.pow(beta, after) * (bound + _KAPPA * (after.clamp(max=8.0) + 2) * u)
    ok = (run < 1.0) | (leak.chain(u, last) - theta > margin_last)
    ok &= (run >= gap.to(f64)) | (theta - leak.chain(u, after) > margin_after)
    if not bool(ok.all()):
        return None
    length = run.to(torch.int64)
    keep = length > 0
    chain_cell, chain_polarity, length = chain_cell[keep], chain_polarity[keep], length[keep]
    return fired_cells, chain_cell, chain_polarity, cell_step[chain_cell] + 1, length


def _greedy_firings(
    inputs: Tensor, scale: Tensor, *, theta: float, beta: float, reset: str
) -> Tensor:
    """Every neuron's firings, one firing of every neuron per pass, by binary search.

    Scaled by ``beta ** -(s_k - s_0)``, a neuron's membrane at cell ``k`` exceeds the
    threshold when ``X_k = S_k - theta * scale_k`` (``S``: its cumulative scaled input)
    exceeds ``D``, the scaled resets of its firings so far (reset "subtract": ``D`` grows by
    ``theta * scale_i / beta`` at a firing at cell ``i``; reset "zero": the membrane restarts
    after it, ``D = S_i``). After a firing at ``i`` the next one is the first cell after ``i``
    whose ``X`` exceeds ``D``: the first cell whose running maximum of ``X`` exceeds ``D``,
    once the ``X`` up to ``i`` are masked out where one of them exceeds ``D`` (a neuron still
    above threshold after its reset). In exact arithmetic these are the firings of the
    recurrence; the caller checks them against the float64 membranes.

    Returns:
        ``(2, R, width)`` bool, the firings (on pads too; the caller masks them).
    """
    lead = inputs.shape[:-1]
    width = inputs.shape[-1]
    device = inputs.device
    summed = torch.cumsum(inputs * scale, -1)
    rise = (summed - scale * theta).reshape(-1, width)
    if reset == "none":
        return (rise > 0).view(*lead, width)
    peak = torch.cummax(rise, -1).values.contiguous()
    lanes = peak.shape[0]
    step = torch.full((lanes, width + 1), math.inf, dtype=inputs.dtype, device=device)
    if reset == "subtract":
        step[:, :width] = (scale * (theta / beta)).expand(*lead, width).reshape(-1, width)
    else:
        step[:, :width] = summed.reshape(-1, width)
    columns = torch.arange(width, device=device)
    debt = torch.zeros(lanes, 1, dtype=inputs.dtype, device=device)
    last = torch.full((lanes, 1), -1, dtype=torch.int64, device=device)  # (no more: D = inf)
    firings = []
    for _ in range(width):
        at = torch.searchsorted(peak, debt, right=True)  # (lanes, 1); width: none left
        behind = (at <= last) & (at < width)  # an X up to the last firing exceeds D
        if bool(behind.any()):
            rows = behind.nonzero()[:, 0]
            masked = rise[rows].masked_fill_(columns <= last[rows], -math.inf)
            peak[rows] = torch.cummax(masked, -1).values
            at[rows] = torch.searchsorted(peak[rows], debt[rows], right=True)
        if int(at.min()) == width:
            break
        firings.append(at)
        last = at
        if reset == "subtract":
            debt = debt + step.gather(1, at)
        else:
            debt = step.gather(1, at)
    fired = torch.zeros(lanes, width + 1, dtype=torch.bool, device=device)
    if firings:
        fired.scatter_(1, torch.cat(firings, 1), True)
    return fired[:, :width].reshape(*lead, width)
