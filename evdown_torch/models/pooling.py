"""Spiking pooling: one leaky integrate-and-fire neuron per output region and polarity."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import snntorch
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from evdown_torch.checks import (
    check_choice,
    check_factor,
    check_non_negative_float,
    check_positive_float,
    check_unit_interval,
    output_size,
)
from evdown_torch.models._snn import unregistered
from evdown_torch.transforms.functional.lif import (
    DEFAULT_THRESHOLD,
    DEFAULT_WEIGHT,
    RESET_MECHANISMS,
    ResetMechanism,
    decay_factor,
)

__all__ = ["SpikingPooling", "decay_factor", "resolve_beta"]

#: The module's leak when neither ``tau`` nor ``beta`` is given: ``tau`` = 10 steps.
DEFAULT_TAU_STEPS = 10.0


def resolve_beta(*, tau: float | None, beta: float | None, dt: float) -> float:
    """The decay factor from exactly one of ``tau`` (with ``dt``) and ``beta``.

    Raises:
        ValueError: if both ``tau`` and ``beta`` are given, or a value is out of range.
    """
    if tau is not None and beta is not None:
        raise ValueError(
            f"give the leak as tau or as beta, not both; got tau={tau!r} and beta={beta!r}"
        )
    if beta is not None:
        return check_unit_interval("beta", beta)
    return decay_factor(dt, DEFAULT_TAU_STEPS * dt if tau is None else tau)


class SpikingPooling(nn.Module):
    r"""Spiking pooling: a fixed pooling convolution followed by ``snntorch.Leaky`` neurons.

    Each ``fx x fy`` block of input pixels drives one leaky integrate-and-fire neuron per
    polarity. The input current of neuron ``(c, i, j)`` at step ``k`` is the convolution with
    kernel = stride = ``(fy, fx)`` (the last row/column of blocks zero-padded at the
    bottom/right when ``H``/``W`` is not a multiple of the factor),

    .. math::

        I_k[c, i, j] = w \, S_k[c, i, j] - w_{inh} \, S_k[1 - c, i, j], \qquad
        S_k[c, i, j] = \sum_{(y, x) \in \text{block}(i, j)} x_k[c, y, x],

    that is, weight ``+w`` from same-polarity inputs and ``-w_inh`` from the opposite polarity
    (:attr:`conv_weight` is that kernel, ``(2, 2, fy, fx)``). It is computed as exact sum
    pooling followed by the channel mixing above, so integer spike counts are summed exactly.
    The neurons are one ``snntorch.Leaky`` (default ATan surrogate gradient), with its exact
    semantics: with ``R_k = [U_{k-1} > \theta]`` (the reset comes from the *previous* step),

    - ``"subtract"``: ``U_k = beta * U_{k-1} + I_k - R_k * theta``;
    - ``"zero"``: ``U_k = beta * (1 - R_k) * U_{k-1} + I_k``;
    - ``"none"``: ``U_k = beta * U_{k-1} + I_k``;

    and the neuron spikes at step ``k`` when ``U_k > theta`` (strictly). A membrane still above
    threshold after a spike therefore keeps spiking in the next steps even without input.

    The leak is set by exactly one of ``tau`` and ``beta``, with ``beta = exp(-dt / tau)``;
    ``tau`` is in the unit of ``dt`` (``dt = 1`` by default: ``tau`` counted in steps), so
    ``tau -> 0`` gives ``beta = 0`` (no memory) and ``tau = math.inf`` gives ``beta = 1``
    (integrate-and-fire). With neither, ``tau`` is 10 steps.

    Constants live in buffers (``weight``, ``mutual_inhibition`` here and ``neuron.beta``,
    ``neuron.threshold`` in the Leaky), so ``state_dict``, ``.to(device)`` and ``torch.compile``
    work; with ``learnable=True``, ``weight`` and ``mutual_inhibition`` are ``nn.Parameter``\ s.
    (snntorch picks the reset rule when the Leaky is built, so load a state dict into a module
    built with the same ``reset_mechanism``.)

    Args:
        factor: ``f`` or ``(fx, fy)``, positive integers: block width and height.
        tau: membrane time constant, in the unit of ``dt``, positive (``math.inf``: no leak).
        beta: membrane decay per step in ``[0, 1]``, instead of ``tau``.
        dt: length of a time step, used only to turn ``tau`` into ``beta``.
        threshold: firing threshold ``theta``, positive.
        weight: ``w``, weight of each same-polarity input pixel, positive.
        mutual_inhibition: ``w_inh >= 0``, weight of each opposite-polarity input pixel,
            subtracted (0: no inhibition).
        reset_mechanism: ``"subtract"``, ``"zero"`` or ``"none"`` (snntorch's meanings).
        learnable: make ``weight`` and ``mutual_inhibition`` trainable parameters.
        spike_grad: snntorch surrogate gradient (``None``: snntorch's default ATan).

    Shape:
        - Input: ``(T, B, 2, H, W)`` spikes or spike counts, time first, channel 0 OFF and
          channel 1 ON (Tonic's ``ToFrame`` order); float, integer or bool.
        - State: membrane ``(B, 2, ceil(H / fy), ceil(W / fx))``.
        - Output: spikes ``(T, B, 2, ceil(H / fy), ceil(W / fx))``, float 0/1.

    Example:
        >>> pool = SpikingPooling(2, beta=1.0, weight=0.25, threshold=1.0)
        >>> x = torch.zeros(6, 1, 2, 2, 2)
        >>> x[:, 0, 1, 0, 0] = 1.0  # one ON event per step in the block
        >>> spikes, mem = pool(x)
        >>> spikes[:, 0, 1, 0, 0].tolist()  # fires once the membrane exceeds 1
        [0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        >>> mem[0, 1].tolist()
        [[0.5]]
    """

    def __init__(
        self,
        factor: int | tuple[int, int],
        *,
        tau: float | None = None,
        beta: float | None = None,
        dt: float = 1.0,
        threshold: float = DEFAULT_THRESHOLD,
        weight: float = DEFAULT_WEIGHT,
        mutual_inhibition: float = 0.0,
        reset_mechanism: ResetMechanism = "subtract",
        learnable: bool = False,
        spike_grad: Callable[[Tensor], Tensor] | None = None,
    ) -> None:
        super().__init__()
        self.factor = check_factor(factor)
        beta = resolve_beta(tau=tau, beta=beta, dt=dt)
        threshold = check_positive_float("threshold", threshold)
        weight = check_positive_float("weight", weight)
        inhibition = check_non_negative_float("mutual_inhibition", mutual_inhibition)
        check_choice("reset_mechanism", reset_mechanism, RESET_MECHANISMS)
        if not isinstance(learnable, bool):
            raise TypeError(f"learnable must be a bool, got {learnable!r}")
        self.learnable = learnable
        for name, value in (("weight", weight), ("mutual_inhibition", inhibition)):
            tensor = torch.tensor(value, dtype=torch.float32)
            if learnable:
                self.register_parameter(name, nn.Parameter(tensor))
            else:
                self.register_buffer(name, tensor)
        self.neuron = unregistered(
            snntorch.Leaky(
                beta=torch.tensor(beta, dtype=torch.float32),
                threshold=torch.tensor(threshold, dtype=torch.float32),
                reset_mechanism=reset_mechanism,
                spike_grad=spike_grad,
            )
        )

    @property
    def beta(self) -> float:
        """Membrane decay per step (float32 value in the neuron's buffer)."""
        return float(self.neuron.beta)

    @property
    def threshold(self) -> float:
        """Firing threshold (float32 value in the neuron's buffer)."""
        return float(self.neuron.threshold)

    @property
    def reset_mechanism(self) -> str:
        """``"subtract"``, ``"zero"`` or ``"none"``."""
        return self.neuron.reset_mechanism

    @property
    def conv_weight(self) -> Tensor:
        """The equivalent ``conv2d`` kernel ``(2, 2, fy, fx)`` (``+w`` same, ``-w_inh`` other)."""
        fx, fy = self.factor
        same = torch.eye(2, dtype=self.weight.dtype, device=self.weight.device)
        mix = self.weight * same - self.mutual_inhibition * (1 - same)
        return mix[:, :, None, None].expand(2, 2, fy, fx)

    def output_shape(self, height: int, width: int) -> tuple[int, int]:
        """Output ``(ceil(H / fy), ceil(W / fx))`` for an input of ``H x W`` pixels."""
        fx, fy = self.factor
        return -(-height // fy), -(-width // fx)

    def current(self, x: Tensor) -> Tensor:
        """Input current of the neurons: the pooling convolution of ``x``.

        Args:
            x: ``(..., 2, H, W)`` spikes (any leading dimensions, e.g. ``(T, B)``).

        Returns:
            ``(..., 2, ceil(H / fy), ceil(W / fx))`` currents, in ``x``'s floating dtype
            (float32 for integer or bool input).
        """
        if x.ndim < 3 or x.shape[-3] != 2:
            raise ValueError(
                "spikes must have shape (..., 2, H, W) with channels (OFF, ON), "
                f"got shape {tuple(x.shape)}"
            )
        if not x.is_floating_point():
            x = x.to(self.weight.dtype)
        fx, fy = self.factor
        *lead, _, height, width = x.shape
        ho, wo = self.output_shape(height, width)
        x = F.pad(x, (0, wo * fx - width, 0, ho * fy - height))
        pooled = x.reshape(*lead, 2, ho, fy, wo, fx).sum(dim=(-3, -1))
        return self.weight * pooled - self.mutual_inhibition * pooled.flip(-3)

    def step(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Advance the neurons by one time step.

        Args:
            x: ``(B, 2, H, W)`` input spikes of this step.
            state: ``(B, 2, Ho, Wo)`` membrane after the previous step; ``None``: zero.

        Returns:
            ``(spikes, state)``: this step's spikes and membrane, both ``(B, 2, Ho, Wo)``.
        """
        if x.ndim != 4:
            raise ValueError(
                f"one step of spikes must have shape (B, 2, H, W), got {tuple(x.shape)}"
            )
        spikes, state = self(x.unsqueeze(0), state)
        return spikes[0], state

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Pool and integrate a time-first spike tensor.

        Args:
            x: ``(T, B, 2, H, W)`` input spikes (channel 0 OFF, 1 ON).
            state: ``(B, 2, Ho, Wo)`` membrane to start from; ``None`` starts from zero.

        Returns:
            ``(spikes, state)``: ``(T, B, 2, Ho, Wo)`` output spikes and the membrane after
            the last step.
        """
        if x.ndim != 5 or x.shape[2] != 2:
            raise ValueError(
                "spikes must have shape (T, B, 2, H, W), time first, channels (OFF, ON); "
                f"got shape {tuple(x.shape)}"
            )
        current = self.current(x)
        if state is None:
            state = torch.zeros_like(current[0])
        elif state.shape != current.shape[1:]:
            raise ValueError(
                f"state must have shape {tuple(current.shape[1:])} (B, 2, Ho, Wo) for input "
                f"of shape {tuple(x.shape)}, got {tuple(state.shape)}"
            )
        if x.shape[0] == 0:
            return torch.zeros_like(current), state
        spikes = []
        for k in range(x.shape[0]):
            spike, state = self.neuron(current[k], state)
            spikes.append(spike)
        self.neuron.mem = torch.zeros(0, device=state.device)  # keep no hidden state
        return torch.stack(spikes), state

    def extra_repr(self) -> str:
        fx, fy = self.factor
        return (
            f"factor=({fx}, {fy}), beta={self.beta:.6g}, threshold={self.threshold:.6g}, "
            f"weight={float(self.weight):.6g}, "
            f"mutual_inhibition={float(self.mutual_inhibition):.6g}, "
            f"reset_mechanism={self.reset_mechanism!r}, learnable={self.learnable}"
        )
