"""LIF pooling's compiled loop: the rounds of snntorch's float32 update, cell after cell.

The eager kernel (:func:`~evdown_torch.transforms.functional.lif.rounds.membranes_by_rounds`)
updates the ``r``-th cell of every region at once, a fixed few tensor operations per round;
this loop runs the same rounds, lane by lane, with the same float32 operations in the same
order (a product, a sum, a difference: each rounded once, as torch rounds them), reading the
same decays ``beta ** g`` (computed once for every cell by
:mod:`~evdown_torch.transforms.functional.lif.powers`). A neuron that goes on firing through
empty steps (reset "subtract") runs the first steps of its chain as
:meth:`~evdown_torch.transforms.functional.lif.chains.Leak.fire_through` runs them (its
:data:`~evdown_torch.transforms.functional.lif.chains.EXACT_CHAIN_STEPS` float32 steps), then
decays by the power of the steps left, read from the same table of powers
(:attr:`~evdown_torch.transforms.functional.lif.powers.Powers.small_float32`). A round in which
a chain outlasts those steps (the closed form's) or decays over ``2 ** LOW_BITS`` steps or
more is left to the eager round; the loop then continues after it. Both paths give the same
membranes, bit for bit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.lif.chains import EXACT_CHAIN_STEPS

if TYPE_CHECKING:
    from evdown_torch.transforms.functional.lif.chains import Leak, Rounds

__all__ = ["rounds_until_chain"]

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
def _rounds_loop(
    membrane: np.ndarray, current: np.ndarray, decay: np.ndarray, decay_after_one: np.ndarray,
    silent: np.ndarray, gap: np.ndarray, chain_count: np.ndarray, bounds: np.ndarray,
    start: int, stop: int, beta: np.float32, threshold: np.float32, reset: int,
    powers: np.ndarray, exact_steps: int,
) -> int:  # pragma: no cover - compiled
    """Rounds ``start .. stop - 1`` of the update, in place in ``membrane`` (``(n, 2)`` float32).

    Lane ``i`` of round ``r`` (row ``bounds[r] + i``) continues lane ``i`` of round ``r - 1``.
    ``reset``: 0 subtract, 1 zero, 2 none.

    Returns:
        ``stop``, or the first round (not computed) in which a firing chain is one the loop
        cannot follow (:func:`_chain`).
    """
    zero = np.float32(0.0)
    for r in range(start, stop):
        a = bounds[r]
        b = bounds[r + 1]
        previous = bounds[r - 1] - a  # lane i's row in round r - 1, less its row in round r
        if reset == 0:
            for i in range(a, b):
                if silent[i]:
                    for c in range(2):
                        u = membrane[previous + i, c]
                        if u > threshold and beta * u - threshold > threshold:
                            ok, _, _, _ = _chain(u, gap[i], beta, threshold, powers,
                                                 exact_steps)
                            if not ok:
                                return r
        for i in range(a, b):
            for c in range(2):
                u = membrane[previous + i, c]
                fired = u > threshold
                w = u * decay[i]
                if reset == 1:
                    if fired:
                        w = zero
                elif reset == 0 and fired and silent[i]:  # one step of the chain, then decay
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
    return stop


def rounds_until_chain(rounds: Rounds, start: int, leak: Leak) -> int:
    """The eager rounds from ``start`` on, compiled, up to one whose chain it cannot follow.

    Args:
        rounds: the cells in round order (their membranes are written in place).
        start: the first round to compute, ``>= 1``.
        leak: the neurons' ``beta``, threshold and reset.

    Returns:
        The number of rounds when all are computed, else the first round not computed (one
        with a firing chain longer than ``EXACT_CHAIN_STEPS`` steps, or decaying over
        ``2 ** LOW_BITS`` steps or more after its chain: the eager round's).
    """
    return int(_rounds_loop(
        rounds.membrane.numpy(), rounds.current.numpy(), rounds.decay.numpy().reshape(-1),
        rounds.decay_after_one.numpy().reshape(-1), rounds.silent.numpy().reshape(-1),
        rounds.gap.numpy().reshape(-1), rounds.chain.numpy(),
        np.asarray(rounds.bounds, dtype=np.int64), start, len(rounds.bounds) - 1,
        np.float32(leak.beta), np.float32(leak.threshold), _RESETS[leak.reset],
        leak.powers.small_float32.numpy(), EXACT_CHAIN_STEPS,
    ))
