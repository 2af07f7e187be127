"""What the models share about snntorch neurons."""

from __future__ import annotations

import weakref
from typing import Any, NoReturn

import snntorch
import torch
from torch import Tensor


class Surrogate:
    """A snntorch surrogate gradient as an object that pickles.

    snntorch's ``surrogate.atan()`` and ``surrogate.fast_sigmoid(slope)`` return local
    closures, which ``pickle`` (and so ``torch.save(model)`` of a whole model) cannot store.
    This computes the same, ``function.apply(x, parameter)``, from snntorch's module-level
    autograd function and its parameter.

    Args:
        function: snntorch's autograd function, e.g. ``snntorch.surrogate.ATan``.
        parameter: its parameter (ATan's ``alpha``, FastSigmoid's ``slope``).
    """

    def __init__(self, function: type[torch.autograd.Function], parameter: float) -> None:
        self.function, self.parameter = function, parameter

    def __call__(self, x: Tensor) -> Tensor:
        return self.function.apply(x, self.parameter)

    def __repr__(self) -> str:
        return f"Surrogate({self.function.__name__}, {self.parameter!r})"


def unregistered(neuron: snntorch.SpikingNeuron) -> snntorch.SpikingNeuron:
    """Take a neuron out of snntorch's class-level registry and return it.

    snntorch lists every neuron ever built in ``SpikingNeuron.instances`` for its hidden-state
    helpers. Our modules keep their state explicit and never use that registry; leaving a
    neuron in it would keep every discarded model alive.
    """
    instances = snntorch.SpikingNeuron.instances
    for i, other in enumerate(instances):
        if other is neuron:
            del instances[i]
            break
    return neuron


class _ResetHandle(snntorch.Leaky):
    """Stands for one stateful layer in snntorch's registry, holding it only weakly.

    ``snntorch.utils.reset(net)`` looks at ``net``'s direct children; when one is a
    ``snntorch.Leaky`` it calls ``snntorch.Leaky.reset_hidden()`` and ``detach_hidden()``,
    which set ``mem`` to zeros and detach it on every ``Leaky`` in the class-level registry
    ``SpikingNeuron.instances``. This handle is such a ``Leaky`` (built without Leaky's own
    ``__init__``: no buffers, no registration of its own): reading ``mem`` gives the layer's
    membrane (an empty tensor when there is none) and setting it calls the layer's ``reset()``.
    The registry holds the handle, not the layer, and the handle leaves it when the layer is
    freed, so that discarded models are not kept alive.
    """

    def __init__(self, layer: torch.nn.Module) -> None:
        torch.nn.Module.__init__(self)
        self._layer = weakref.ref(layer)

    @property
    def mem(self) -> Tensor:
        layer = self._layer()
        mem = None if layer is None else layer.mem
        return mem if isinstance(mem, Tensor) else torch.zeros(0)

    @mem.setter
    def mem(self, value: Tensor) -> None:
        layer = self._layer()
        if layer is not None:
            layer.reset()  # type: ignore[operator]  # the layer's own reset()

    def forward(self, *args: object, **kwargs: object) -> NoReturn:  # never in a network
        raise TypeError("a reset handle only stands in snntorch's registry")


def _drop_handle(handle: _ResetHandle) -> None:
    instances = snntorch.SpikingNeuron.instances  # snntorch may have replaced the list
    for i, other in enumerate(instances):
        if other is handle:
            del instances[i]
            break


def register_for_snntorch_reset(layer: torch.nn.Module) -> None:
    """Let ``snntorch.utils.reset`` reset ``layer`` as it resets ``snntorch.Leaky`` neurons.

    ``layer`` has ``mem`` and ``reset()``; the registry does not keep it alive.
    """
    handle = _ResetHandle(layer)
    snntorch.SpikingNeuron.instances.append(handle)
    weakref.finalize(layer, _drop_handle, handle)


def leaky_through_time(
    neuron: snntorch.Leaky, current: Tensor, mem: Tensor, slope: float
) -> tuple[Tensor, Tensor]:
    """Step a ``snntorch.Leaky`` neuron through every time step of ``current`` at once.

    The same arithmetic as calling ``neuron(current[t], mem)`` for each ``t`` in turn, for the
    configuration the models build (subtract reset one step after the spike, a fast-sigmoid
    surrogate of ``slope``, spikes of 1, fixed ``beta`` and ``threshold``): the membrane is
    ``mem_t = beta * mem_{t-1} + current[t] - threshold * [mem_{t-1} > threshold]`` and the
    spike ``[mem_t > threshold]``, with the reset detached from the graph, and the gradient of
    a spike is ``1 / (slope * |mem_t - threshold| + 1) ** 2``. Stepping the snntorch module
    records about fifteen small operations per step in the autograd graph; this records one
    node and runs four operations per step forward and two backward, with the same float32
    roundings (the tests compare both, outputs and gradients, bit for bit).

    Args:
        neuron: the snntorch neuron, for its ``beta`` and ``threshold``.
        current: ``[T, ...]`` float input current of each step.
        mem: ``[...]`` membrane before the first step.
        slope: the slope of the neuron's fast-sigmoid surrogate gradient.

    Returns:
        ``(spikes, membranes)``, both ``[T, ...]`` like ``current``.

    Raises:
        ValueError: for a neuron with a learnable ``beta`` or ``threshold``.
    """
    beta, threshold = neuron.beta, neuron.threshold
    if beta.requires_grad or threshold.requires_grad:
        raise ValueError("leaky_through_time needs a fixed beta and threshold (not learnable)")
    return _LeakyThroughTime.apply(current, mem, beta.clamp(0, 1), threshold, float(slope))


class _LeakyThroughTime(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, current: Tensor, mem: Tensor, beta: Tensor, threshold: Tensor,
                slope: float) -> tuple[Tensor, Tensor]:
        membranes = torch.empty_like(current)
        spikes = torch.empty_like(current)
        step = float(threshold)  # subtracting reset * threshold, reset in {0, 1}, is exact
        reset = (mem > threshold).to(current.dtype)
        for t in range(current.shape[0]):
            now = membranes[t]
            torch.mul(beta, mem, out=now)
            now.add_(current[t])
            now.sub_(reset, alpha=step)
            reset = spikes[t]
            torch.gt(now, threshold, out=reset)
            mem = now
        ctx.save_for_backward(membranes, beta, threshold)
        ctx.slope = slope
        return spikes, membranes

    @staticmethod
    def backward(ctx: Any, grad_spikes: Tensor, grad_membranes: Tensor | None
                 ) -> tuple[Tensor, Tensor, None, None, None]:
        membranes, beta, threshold = ctx.saved_tensors
        grad = grad_spikes / (ctx.slope * torch.abs(membranes - threshold) + 1.0) ** 2
        if grad_membranes is not None:
            grad = grad + grad_membranes
        # The gradient reaching mem_t: its own spike's (and membrane's), plus beta times
        # mem_{t+1}'s; the reset is detached. Accumulated in place, last step first.
        later = grad[-1]
        for t in range(grad.shape[0] - 2, -1, -1):
            later = grad[t].add_(beta * later)
        return grad, beta * later, None, None, None
