"""A LIF neuron without input: decay over empty steps and firing chains, in closed form.

Used by :mod:`evdown_torch.transforms.functional.lif.pooling`: between two steps with input, a
neuron decays by ``beta ** gap``; one left above threshold keeps firing through the silence
(resets "subtract" and "none"), the first :data:`EXACT_CHAIN_STEPS` steps with snntorch's
float32 arithmetic and the rest of the chain in closed form, never step by step.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch.transforms.functional.lif.powers import powers_of
from evdown_torch.transforms.functional.lif.steps import MAX_STEPS

__all__ = ["EXACT_CHAIN_STEPS", "CellSpikes", "Leak", "Rounds"]

#: Steps of a firing chain computed with snntorch's float32 arithmetic, one at a time, before
#: the closed form takes over (a chain rarely lasts longer unless ``beta`` is about 1).
EXACT_CHAIN_STEPS = 8


class Rounds(NamedTuple):
    """The cells in round order (round ``r``: rows ``bounds[r] .. bounds[r + 1] - 1``).

    ``membrane``, ``current``: ``(n, 2)`` float32; ``decay``, ``decay_after_one``: ``(n, 1)``
    float32 ``beta ** g`` and ``beta ** (g - 1)`` of the gap ``g`` before each cell
    (``gap``, ``(n, 1)`` int64; ``silent``: ``g > 0``); ``chain``: ``(n, 2)`` int64 spikes
    fired in the gap. ``membrane`` and ``chain`` are written round by round.
    """

    membrane: Tensor
    current: Tensor
    decay: Tensor
    decay_after_one: Tensor
    silent: Tensor
    gap: Tensor
    chain: Tensor
    bounds: list[int]


class CellSpikes(NamedTuple):
    """The spikes of a call's cells, as the rounds and the closed form both return them.

    Attributes:
        spike_cell: ``(S,)`` int64 cell of every spike at a cell (cell-major).
        spike_polarity: ``(S,)`` int64 neuron (0 OFF, 1 ON) of every such spike.
        run_cell: ``(U,)`` int64 cell after which a neuron fires on through empty steps.
        run_polarity: ``(U,)`` int64 neuron of every run.
        run_start: ``(U,)`` int64 step of every run's first spike.
        run_length: ``(U,)`` int64 spikes of every run (one per step from ``run_start``).
    """

    spike_cell: Tensor
    spike_polarity: Tensor
    run_cell: Tensor
    run_polarity: Tensor
    run_start: Tensor
    run_length: Tensor


class Leak:
    """A neuron without input, for one ``(beta, threshold, reset)``: decay and firing chains.

    Membranes are float32 as in snntorch; the closed forms run in float64 on exact copies.
    Every power ``beta ** j`` is :attr:`powers`' (a function of ``j`` alone, not of where
    ``j`` lies: :mod:`~evdown_torch.transforms.functional.lif.powers`).
    """

    def __init__(self, beta: Tensor, threshold: Tensor, reset: str) -> None:
        self.beta32, self.threshold32, self.reset = beta, threshold, reset
        self.beta, self.threshold = float(beta), float(threshold)
        b = self.beta
        self.log_beta = math.log(b) if 0.0 < b < 1.0 else 0.0
        self.offset = self.threshold / (1.0 - b) if b < 1.0 else math.inf  # A, module docstring
        self.powers = powers_of(b, beta.device)

    def decay(self, u: Tensor, steps: Tensor) -> Tensor:
        """``u`` after int64 ``steps`` steps of pure decay: ``u * beta ** steps`` (float32)."""
        return u * self.powers.float32(steps)

    def chain(self, u: Tensor, j: Tensor) -> Tensor:
        """Membrane ``j`` steps after ``u``, firing (and resetting) at every one.

        Float64 ``u`` and ``j`` (whole numbers, at least 0).
        """
        b, theta = self.beta, self.threshold
        if self.reset == "none":
            return u * self.powers.float64(j) if b < 1.0 else u
        if b == 1.0:
            return u - j * theta
        return self.powers.float64(j) * (u + self.offset) - self.offset  # b = 0: -theta, j >= 1

    def run(self, u: Tensor) -> Tensor:
        """Number of ``j >= 1`` at which the chain from ``u > threshold`` stays above it.

        Float64 in and out; "none" with ``beta = 1`` never stops (returns ``MAX_STEPS``).
        """
        b, theta = self.beta, self.threshold
        if self.reset == "zero" or b == 0.0 or u.numel() == 0:
            return torch.zeros_like(u)
        if self.reset == "none":
            if b == 1.0:
                return torch.full_like(u, float(MAX_STEPS))
            bound = torch.log(theta / u) / self.log_beta  # b^j u > theta  <=>  j < bound
        elif b == 1.0:
            bound = u / theta - 1.0  # u - j theta > theta  <=>  j < u / theta - 1
        else:  # b^j (u + A) - A > theta  <=>  j < log((theta + A) / (u + A)) / log(b)
            bound = torch.log((theta + self.offset) / (u + self.offset)) / self.log_beta
        count = (torch.ceil(bound) - 1.0).clamp(0.0, float(MAX_STEPS))
        # Settle the rounding of the logarithms on the chain's own values.
        count -= ((count >= 1.0) & (self.chain(u, count) <= theta)).to(count.dtype)
        count += (self.chain(u, count + 1.0) > theta).to(count.dtype)
        return count.clamp_(0.0, float(MAX_STEPS))

    def fire_through(
        self, u: Tensor, gap: Tensor, alive: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Neurons that fired (float32 membrane ``u > threshold``), then ``gap`` empty steps.

        The first :data:`EXACT_CHAIN_STEPS` steps of a chain use snntorch's float32
        arithmetic, all lanes at once; a chain still firing after them continues in closed
        form.

        Args:
            u: float32 membranes, above threshold where ``alive``.
            gap: int64 numbers of empty steps, broadcastable to ``u``, at least 1 where
                ``alive``.
            alive: bool, the lanes to compute; the others are returned as they came
                (``count`` 0, ``W = u``, ``R = u > threshold``).

        Returns:
            ``(count, W, R)``: int64 spikes fired in the gap (in its first ``count`` steps),
            float32 membranes after the gap and bool resets (fired at its last step).
        """
        if self.reset == "zero":  # reset to zero at the first empty step: silent afterwards
            return (torch.zeros(u.shape, dtype=torch.int64, device=u.device),
                    u.masked_fill(alive, 0.0), (u > self.threshold32) & ~alive)
        v = u
        took_step = []  # per step: the lanes that took it (a chain stops for good)
        fired = []  # per step: the lanes that fired in it
        for j in range(EXACT_CHAIN_STEPS):  # a bounded number of steps, all lanes at once
            if j and not bool(alive.any()):
                break
            after = self.beta32 * v  # + a zero current: exact
            if self.reset == "subtract":
                after = after - self.threshold32
            v = torch.where(alive, after, v)
            took_step.append(alive)
            alive = alive & (v > self.threshold32)
            fired.append(alive)
            alive = alive & (gap > j + 1)
        steps = torch.stack(took_step).sum(0)
        count = torch.stack(fired).sum(0)
        w = self.decay(v, gap - steps)  # ended chains only decay
        still = v > self.threshold32  # above threshold only where the gap ended the chain
        if bool(alive.any()):  # chains longer than EXACT_CHAIN_STEPS: closed form
            lanes = alive.nonzero(as_tuple=True)
            left = (gap.expand_as(v)[lanes] - steps[lanes]).to(torch.float64)
            v64 = v[lanes].to(torch.float64)
            run = self.run(v64)
            chained = torch.minimum(left, run + 1.0)  # steps of the firing chain, then decay
            w[lanes] = (self.powers.float64(left - chained) * self.chain(v64, chained)).to(u.dtype)
            still[lanes] = run >= left
            count[lanes] += torch.minimum(run, left).to(torch.int64)
        return count, w, still
