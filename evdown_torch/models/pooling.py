"""Spiking pooling: one leaky integrate-and-fire neuron per output region and polarity."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import snntorch
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from evdown_torch.checks import check_factor, output_size
from evdown_torch.models._snn import Surrogate, register_for_snntorch_reset, unregistered
from evdown_torch.transforms.functional.lif.settings import (
    DEFAULT_THRESHOLD,
    DEFAULT_WEIGHT,
    LIFSettings,
    ResetMechanism,
    decay_factor,
)
from evdown_torch.transforms.lif import LIFPooling

__all__ = [
    "SpikingPooling",
    "SpikingPoolingLayer",
    "decay_factor",
    "reset_states",
]


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
    (integrate-and-fire). With neither, ``tau`` is 10 steps. The settings are checked once,
    by :class:`~evdown_torch.transforms.functional.lif.settings.LIFSettings`, the settings
    object :class:`~evdown_torch.LIFPooling` and its kernels share.

    Constants live in buffers (``weight``, ``mutual_inhibition`` here and ``neuron.beta``,
    ``neuron.threshold`` in the Leaky), so ``state_dict``, ``.to(device)`` and ``torch.compile``
    work; with ``learnable=True``, ``weight`` and ``mutual_inhibition`` are ``nn.Parameter``\ s.
    The ``reset_mechanism`` is saved in the state dict too (its extra state): loading a state
    dict saved with another reset mechanism raises a ``ValueError``.

    This module is functional in time: it takes a whole spike tensor and returns
    ``(spikes, state)``. Inside an ``nn.Sequential`` driven one step at a time (the snntorch
    idiom), use :class:`SpikingPoolingLayer` (:meth:`layer`).

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
        spike_grad: snntorch surrogate gradient (``None``: snntorch's default, ATan with
            ``alpha = 2``, as an object that pickles, so ``torch.save`` of a whole model
            works; snntorch's own ``surrogate.atan()`` is a closure that does not).
        batch_first: input and output spikes are ``(B, T, ...)`` (as Tonic's ``PadTensors``
            gives them by default) instead of ``(T, B, ...)``, like PyTorch's RNNs.

    Shape:
        - Input: ``(T, B, 2, H, W)`` spikes or spike counts, time first (``(B, T, 2, H, W)``
          with ``batch_first=True``), channel 0 OFF and channel 1 ON (Tonic's ``ToFrame``
          order); float, integer or bool.
        - State: membrane ``(B, 2, ceil(H / fy), ceil(W / fx))``, float32 (or the module's
          dtype after ``.double()``).
        - Output: spikes of the input's shape order, ``(T, B, 2, ceil(H / fy),
          ceil(W / fx))``, 0/1 in the input's floating dtype (half and bfloat16 included;
          float32 for integer or bool input).

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
        batch_first: bool = False,
    ) -> None:
        super().__init__()
        self.weight: Tensor  # a buffer, or a parameter when learnable
        self.mutual_inhibition: Tensor
        self.factor = check_factor(factor)
        settings = LIFSettings(
            dt=dt, tau=tau, beta=beta, threshold=threshold, weight=weight,
            mutual_inhibition=mutual_inhibition, reset_mechanism=reset_mechanism,
        )
        for name, flag in (("learnable", learnable), ("batch_first", batch_first)):
            if not isinstance(flag, bool):
                raise TypeError(f"{name} must be a bool, got {flag!r}")
        self.learnable = learnable
        self.batch_first = batch_first
        for name, value in (("weight", settings.weight),
                            ("mutual_inhibition", settings.mutual_inhibition)):
            tensor = torch.tensor(value, dtype=torch.float32)
            if learnable:
                self.register_parameter(name, nn.Parameter(tensor))
            else:
                self.register_buffer(name, tensor)
        self.neuron = unregistered(
            snntorch.Leaky(
                beta=torch.tensor(settings.beta, dtype=torch.float32),
                threshold=torch.tensor(settings.threshold, dtype=torch.float32),
                reset_mechanism=settings.reset_mechanism,
                spike_grad=Surrogate(snntorch.surrogate.ATan, 2.0) if spike_grad is None
                else spike_grad,
            )
        )

    @classmethod
    def from_transform(cls, pool: LIFPooling) -> SpikingPooling:
        """The module with a :class:`~evdown_torch.LIFPooling` transform's factor and neurons.

        Run on the stream's frames ``ToFrame(sensor_size, time_window=dt,
        include_incomplete=True)`` (windows from the first event on, as a ``(T, 1, 2, H, W)``
        float tensor), it gives the spikes that the transform turns into events (up to float32
        rounding over silences, see :func:`~evdown_torch.transforms.functional.lif_pooling`).

        Example:
            >>> module = SpikingPooling.from_transform(LIFPooling((8, 8, 2), 2, tau=5000.0))
            >>> module.factor, round(module.beta, 4)
            ((2, 2), 0.8187)
        """
        if not isinstance(pool, LIFPooling):
            raise TypeError(f"from_transform takes a LIFPooling, got {type(pool).__name__}")
        return cls(pool.factor_xy, **pool.settings.neuron.constants._asdict())

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

    def get_extra_state(self) -> dict[str, str]:
        """What the state dict records besides tensors: the reset mechanism."""
        return {"reset_mechanism": self.reset_mechanism}

    def set_extra_state(self, state: dict[str, str]) -> None:
        """Refuse a state dict saved with another reset mechanism (it would behave otherwise).

        Raises:
            ValueError: if the saved ``reset_mechanism`` differs from this module's.
        """
        saved = state.get("reset_mechanism") if isinstance(state, dict) else None
        if saved != self.reset_mechanism:
            raise ValueError(
                f"this state dict was saved from a SpikingPooling with reset_mechanism="
                f"{saved!r}, but this module uses {self.reset_mechanism!r}; build the module "
                f"with reset_mechanism={saved!r} to load it"
            )

    def layer(self) -> SpikingPoolingLayer:
        """A :class:`SpikingPoolingLayer` around this module (sharing its parameters)."""
        return SpikingPoolingLayer(self)

    @property
    def conv_weight(self) -> Tensor:
        """The equivalent ``conv2d`` kernel ``(2, 2, fy, fx)`` (``+w`` same, ``-w_inh`` other)."""
        fx, fy = self.factor
        same = torch.eye(2, dtype=self.weight.dtype, device=self.weight.device)
        mix = self.weight * same - self.mutual_inhibition * (1 - same)
        return mix[:, :, None, None].expand(2, 2, fy, fx)

    def output_shape(self, height: int, width: int) -> tuple[int, int]:
        """Output ``(ceil(H / fy), ceil(W / fx))`` for an input of ``H x W`` pixels."""
        wo, ho, _ = output_size((width, height, 2), self.factor)
        return ho, wo

    def current(self, x: Tensor) -> Tensor:
        """Input current of the neurons: the pooling convolution of ``x``.

        Args:
            x: ``(..., 2, H, W)`` spikes (any leading dimensions, e.g. ``(T, B)``).

        Returns:
            ``(..., 2, ceil(H / fy), ceil(W / fx))`` currents, in ``x``'s floating dtype
            (the module's, float32 by default, for integer or bool input).
        """
        _check_tensor(x, "spikes")
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
        weight, inhibition = self.weight.to(x.dtype), self.mutual_inhibition.to(x.dtype)
        return weight * pooled - inhibition * pooled.flip(-3)

    def step(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Advance the neurons by one time step.

        Args:
            x: ``(B, 2, H, W)`` input spikes of this step.
            state: ``(B, 2, Ho, Wo)`` membrane after the previous step; ``None``: zero.

        Returns:
            ``(spikes, state)``: this step's spikes and membrane, both ``(B, 2, Ho, Wo)``.
        """
        _check_step(x)
        spikes, state = self._run(x.unsqueeze(0), state)
        return spikes[0], state

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Pool and integrate a spike tensor over its time axis.

        Args:
            x: ``(T, B, 2, H, W)`` input spikes, time first; ``(B, T, 2, H, W)`` with
                ``batch_first=True`` (channel 0 OFF, 1 ON).
            state: ``(B, 2, Ho, Wo)`` membrane to start from; ``None`` starts from zero.

        Returns:
            ``(spikes, state)``: output spikes ``(T, B, 2, Ho, Wo)`` (``(B, T, ...)`` with
            ``batch_first=True``) and the membrane after the last step.
        """
        _check_tensor(x, "spikes")
        if x.ndim != 5 or x.shape[2] != 2:
            order = "(B, T, 2, H, W), batch first" if self.batch_first else (
                "(T, B, 2, H, W), time first (batch_first=False)"
            )
            raise ValueError(
                f"spikes must have shape {order}, channels (OFF, ON); "
                f"got shape {tuple(x.shape)}"
            )
        if self.batch_first:
            spikes, state = self._run(x.transpose(0, 1), state)
            return spikes.transpose(0, 1), state
        return self._run(x, state)

    def _run(self, x: Tensor, state: Tensor | None) -> tuple[Tensor, Tensor]:
        """:meth:`forward` on a time-first ``(T, B, 2, H, W)`` tensor."""
        current = self.current(x)
        if state is not None:
            _check_tensor(state, "state", "or None")
        if state is None:
            dtype = torch.promote_types(current.dtype, self.neuron.beta.dtype)
            state = torch.zeros(current.shape[1:], dtype=dtype, device=current.device)
        elif state.shape != current.shape[1:]:
            raise ValueError(
                f"state must have shape {tuple(current.shape[1:])} (B, 2, Ho, Wo) for input "
                f"of shape {tuple(x.shape)} (T, B, 2, H, W), got {tuple(state.shape)}"
            )
        if x.shape[0] == 0:
            return torch.zeros_like(current), state
        spikes = []
        for k in range(x.shape[0]):
            spike, state = self.neuron(current[k], state)
            spikes.append(spike)
        self.neuron.mem = torch.zeros(0, device=state.device)  # keep no hidden state
        return torch.stack(spikes).to(current.dtype), state  # spikes in the input's dtype

    def extra_repr(self) -> str:
        """The settings shown by ``repr``."""
        fx, fy = self.factor
        return (
            f"factor=({fx}, {fy}), beta={self.beta:.6g}, threshold={self.threshold:.6g}, "
            f"weight={self.weight.item():.6g}, "
            f"mutual_inhibition={self.mutual_inhibition.item():.6g}, "
            f"reset_mechanism={self.reset_mechanism!r}, learnable={self.learnable}, "
            f"batch_first={self.batch_first}"
        )


def _check_tensor(value: object, what: str, alternative: str = "") -> None:
    """Refuse a ``value`` that is not a tensor, naming ``what`` and the type it got."""
    if not isinstance(value, Tensor):
        wanted = f"a tensor {alternative}".rstrip()
        raise TypeError(f"{what} must be {wanted}, got {type(value).__name__}")


def _check_step(x: Tensor) -> None:
    """Refuse one step of spikes that is not a ``(B, 2, H, W)`` tensor, naming its shape."""
    _check_tensor(x, "one step of spikes")
    if x.ndim != 4:
        raise ValueError(
            f"one step of spikes must have shape (B, 2, H, W), got {tuple(x.shape)}"
        )


class SpikingPoolingLayer(nn.Module):
    """:class:`SpikingPooling` as a stateful layer for snntorch-style networks.

    snntorch networks are often an ``nn.Sequential`` of layers called once per time step,
    whose neurons keep their membrane between calls (``snn.Leaky(init_hidden=True)``). This
    layer does the same: each call takes one step of spikes, returns this step's spikes only
    and keeps the membrane in :attr:`mem`. Reset it between samples as snntorch's neurons are
    reset: ``snntorch.utils.reset(net)`` resets it with them (it resets every neuron of a kind
    when ``net`` has one of that kind among its direct children, here a ``snntorch.Leaky``:
    this layer answers as one; snntorch's registry holds it weakly, so discarded models are
    freed). :meth:`reset` resets this layer alone, and :func:`reset_states` resets every
    stateful layer of a network, however deeply nested, with or without a ``Leaky``.

    Args:
        factor: a :class:`SpikingPooling` to wrap (its parameters are shared), or the
            ``factor`` of a new one.
        **settings: the other :class:`SpikingPooling` arguments, for a new one.

    Shape:
        - Input: ``(B, 2, H, W)`` spikes of one step (channel 0 OFF, 1 ON).
        - Output: ``(B, 2, ceil(H / fy), ceil(W / fx))`` spikes in the input's floating dtype.

    Example:
        >>> import snntorch as snn
        >>> net = torch.nn.Sequential(
        ...     SpikingPoolingLayer(2, beta=1.0, weight=0.6),
        ...     torch.nn.Flatten(), torch.nn.Linear(2 * 2 * 2, 3),
        ...     snn.Leaky(beta=0.9, init_hidden=True))
        >>> x = torch.ones(5, 1, 2, 4, 4)  # (T, B, 2, H, W)
        >>> out = torch.stack([net(x[k]) for k in range(5)])
        >>> out.shape
        torch.Size([5, 1, 3])
        >>> import snntorch.utils
        >>> _ = snntorch.utils.reset(net)  # snntorch's idiom; reset_states(net) does the same
        >>> net[0].mem is None
        True
    """

    def __init__(self, factor: SpikingPooling | int | tuple[int, int], **settings: Any) -> None:
        super().__init__()
        if isinstance(factor, SpikingPooling):
            if settings:
                raise TypeError(
                    "give either a SpikingPooling to wrap or its settings, not both; got "
                    f"{sorted(settings)}"
                )
            self.pool = factor
        else:
            self.pool = SpikingPooling(factor, **settings)
        #: The membrane after the last step, ``(B, 2, Ho, Wo)``; ``None`` after a reset.
        self.mem: Tensor | None = None
        register_for_snntorch_reset(self)

    def reset(self) -> None:
        """Forget the membrane: the next step starts from zero."""
        self.mem = None

    def __setstate__(self, state: dict) -> None:
        """Copies (``copy.deepcopy``, unpickling) answer ``snntorch.utils.reset`` too."""
        super().__setstate__(state)
        register_for_snntorch_reset(self)

    def forward(self, x: Tensor) -> Tensor:
        """One step: ``(B, 2, H, W)`` spikes in, ``(B, 2, Ho, Wo)`` spikes out."""
        _check_step(x)
        if self.mem is not None and (
            self.mem.shape[0] != x.shape[0] or self.mem.device != x.device
        ):
            raise ValueError(
                f"the layer holds the membrane of a batch of {self.mem.shape[0]} on "
                f"{self.mem.device}, got a step of shape {tuple(x.shape)} on {x.device}; "
                "call reset() (or reset_states(net)) between samples"
            )
        spikes, self.mem = self.pool.step(x, self.mem)
        return spikes


def reset_states(net: nn.Module) -> None:
    """Reset the hidden state of every stateful spiking layer of ``net`` (and ``net``).

    Calls :meth:`SpikingPoolingLayer.reset` on our layers and clears the membrane of every
    snntorch neuron built with ``init_hidden=True``, detached from the graph, wherever it
    sits in ``net`` (``snntorch.utils.reset`` looks only at direct children).
    """
    for module in net.modules():
        if isinstance(module, SpikingPoolingLayer):
            module.reset()
        elif isinstance(module, snntorch.SpikingNeuron) and getattr(module, "init_hidden", False):
            for name in ("mem", "syn", "spk"):
                value = getattr(module, name, None)
                if isinstance(value, Tensor):
                    setattr(module, name, torch.zeros_like(value).detach())
