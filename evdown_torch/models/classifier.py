"""A small convolutional spiking classifier for event frames of any size."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, cast

import snntorch
import torch
from snntorch import surrogate
from torch import Tensor, nn
from torch.nn import functional

from evdown_torch.checks import check_positive_float, check_positive_int
from evdown_torch.models._snn import Surrogate, leaky_through_time, unregistered

__all__ = ["ClassifierState", "SpikingClassifier", "class_scores", "stem_stride_for"]


class ClassifierState(NamedTuple):
    """Membrane potentials of every spiking layer of a :class:`SpikingClassifier`.

    Attributes:
        conv: one ``[B, C_i, H_i, W_i]`` tensor per convolutional block.
        out: ``[B, num_classes]`` membrane of the output layer.
    """

    conv: tuple[Tensor, ...]
    out: Tensor


#: Slope of the fast-sigmoid surrogate gradient of every neuron.
_SLOPE = 25.0


def _run_neuron(
    neuron: snntorch.Leaky, current: Tensor, mem: Tensor, *, keep_membrane: bool = False
) -> tuple[Tensor, Tensor | None, Tensor]:
    """Step ``neuron`` through ``current`` (``[T, ...]``) from membrane ``mem``.

    Returns ``(spikes [T, ...], membranes [T, ...] or None, last membrane)``; the membranes
    of every step are kept only with ``keep_membrane``.
    """
    spikes, membranes = leaky_through_time(neuron, current, mem, _SLOPE)
    return spikes, membranes if keep_membrane else None, membranes[-1]


def _leaky(beta: float, threshold: float) -> snntorch.Leaky:
    neuron = snntorch.Leaky(
        beta=beta, threshold=threshold, spike_grad=Surrogate(surrogate.FastSigmoid, _SLOPE)
    )
    return unregistered(neuron)


class SpikingClassifier(nn.Module):
    """Convolutional leaky integrate-and-fire network classifying event frames.

    Each time step goes through an optional strided stem (a ``stem_stride x stem_stride``
    convolution with the same stride to ``stem_channels`` channels, the input zero-padded on the
    right and bottom to a multiple of the stride), then ``len(channels)`` blocks of ``3x3``
    convolution, ``2x2`` max pooling (rounding up, so a ``1x1`` input stays ``1x1``) and a
    leaky integrate-and-fire layer (``snntorch.Leaky``, subtract reset, fast-sigmoid surrogate
    gradient); then an adaptive average pooling to ``pool_size x pool_size`` (which makes the
    network take any input size), a linear layer and a leaky output layer with one neuron per
    class. The class is read from the output spike counts (:meth:`predict`); train it with a
    snntorch loss on the output spikes, e.g. ``snntorch.functional.mse_count_loss()``.

    Args:
        num_classes: number of classes (11 for DVS128 Gesture).
        in_channels: input channels (2: OFF and ON).
        channels: output channels of each convolutional block.
        pool_size: side of the adaptive pooling's output.
        beta: membrane decay per time step, in ``(0, 1]``.
        threshold: firing threshold of every layer.
        stem_stride: side and stride of the stem convolution (1: no stem). A stride that brings
            a large input down to a small working grid (``stem_stride_for``) keeps the cost
            of the blocks the same for every input size and lets their receptive field cover
            the whole input (with four blocks, a grid of 16 is covered).
        stem_channels: output channels of the stem (default: ``channels[0]``).

    Example:
        >>> import torch
        >>> net = SpikingClassifier(num_classes=3, channels=(4,), pool_size=2)
        >>> spikes, membrane, state = net(torch.rand(5, 2, 2, 9, 7))
        >>> spikes.shape, membrane.shape, state.out.shape
        (torch.Size([5, 2, 3]), torch.Size([5, 2, 3]), torch.Size([2, 3]))
    """

    def __init__(
        self,
        num_classes: int = 11,
        *,
        in_channels: int = 2,
        channels: Sequence[int] = (16, 32),
        pool_size: int = 4,
        beta: float = 0.9,
        threshold: float = 1.0,
        stem_stride: int = 1,
        stem_channels: int | None = None,
    ) -> None:
        super().__init__()
        self.num_classes = check_positive_int("num_classes", num_classes)
        self.in_channels = check_positive_int("in_channels", in_channels)
        if isinstance(channels, (str, bytes)) or not isinstance(channels, Sequence):
            raise TypeError(f"channels must be a sequence of positive integers, got {channels!r}")
        self.channels = tuple(check_positive_int("channels", c) for c in channels)
        if not self.channels:
            raise ValueError("channels must name at least one convolutional block, got ()")
        self.pool_size = check_positive_int("pool_size", pool_size)
        beta = check_positive_float("beta", beta)
        if beta > 1:
            raise ValueError(f"beta must lie in (0, 1], got {beta!r}")
        threshold = check_positive_float("threshold", threshold)
        self.stem_stride = check_positive_int("stem_stride", stem_stride)
        if stem_channels is None:
            stem_channels = self.channels[0]
        self.stem_channels = check_positive_int("stem_channels", stem_channels)
        self.stem = (
            nn.Conv2d(self.in_channels, self.stem_channels, kernel_size=self.stem_stride,
                      stride=self.stem_stride)
            if self.stem_stride > 1 else None
        )
        first = self.stem_channels if self.stem is not None else self.in_channels
        widths = (first, *self.channels)
        self.convs = nn.ModuleList(
            nn.Conv2d(a, b, kernel_size=3, padding=1) for a, b in zip(widths, widths[1:])
        )
        self.pool = nn.MaxPool2d(2, ceil_mode=True)
        self.conv_neurons = nn.ModuleList(_leaky(beta, threshold) for _ in self.channels)
        self.squeeze = nn.AdaptiveAvgPool2d(self.pool_size)
        self.fc = nn.Linear(self.channels[-1] * self.pool_size**2, self.num_classes)
        self.out_neuron = _leaky(beta, threshold)

    def extra_repr(self) -> str:
        """The settings shown by ``repr``."""
        return (
            f"num_classes={self.num_classes}, channels={self.channels}, "
            f"pool_size={self.pool_size}, stem_stride={self.stem_stride}, "
            f"beta={float(self.out_neuron.beta):g}, "
            f"threshold={float(self.out_neuron.threshold):g}"
        )

    def initial_state(self, x: Tensor) -> ClassifierState:
        """Zero membranes (in the parameters' dtype) for a ``[T, B, C, H, W]`` input."""
        _, b, _, h, w = x.shape
        dtype = self.fc.weight.dtype
        if self.stem is not None:
            h, w = -(-h // self.stem_stride), -(-w // self.stem_stride)
        conv = []
        for c in self.channels:
            h, w = -(-h // 2), -(-w // 2)
            conv.append(torch.zeros(b, c, h, w, dtype=dtype, device=x.device)
                        .contiguous(memory_format=torch.channels_last))
        return ClassifierState(tuple(conv), torch.zeros(b, self.num_classes, dtype=dtype,
                                                        device=x.device))

    def forward(
        self, x: Tensor, state: ClassifierState | None = None
    ) -> tuple[Tensor, Tensor, ClassifierState]:
        """Run the network over the time steps of ``x``.

        Args:
            x: ``[T, B, in_channels, H, W]`` input (event counts or spikes, any real dtype:
                it is copied once into the parameters' dtype), any ``H, W >= 1``.
            state: membranes to start from; zeros by default.

        Returns:
            ``(spikes, membrane, state)``: output spikes and output membrane, both
            ``[T, B, num_classes]``, and the state after the last step.
        """
        if x.ndim != 5 or x.shape[2] != self.in_channels:
            raise ValueError(
                f"input must have shape [T, B, {self.in_channels}, H, W], "
                f"got {tuple(x.shape)}"
            )
        if state is None:
            state = self.initial_state(x)
        steps, batch = x.shape[:2]
        # Layer by layer: the convolutions, pooling and linear layer hold no state, so each
        # runs once over all time steps (a batch of T * B); only the neurons step through time.
        # This is the same network as running each time step through every layer in turn.
        # Channels-last tensors take oneDNN's faster convolution and pooling paths on CPU.
        # One copy, whatever the layout and floating dtype of x, into the parameters' dtype.
        flat = torch.empty((steps * batch, *x.shape[2:]), dtype=self.fc.weight.dtype,
                           device=x.device, memory_format=torch.channels_last)
        flat.unflatten(0, (steps, batch)).copy_(x)
        current = self._stem(flat)
        conv_mem = []
        for conv, neuron, mem in zip(self.convs, self.conv_neurons, state.conv):
            current = self.pool(conv(current))
            current, _, mem = _run_neuron(neuron, current.unflatten(0, (steps, batch)), mem)
            conv_mem.append(mem)
            current = current.flatten(0, 1)
        if current.shape[-2:] != (self.pool_size, self.pool_size):  # else the identity
            current = self.squeeze(current)
        current = self.fc(current.flatten(1)).unflatten(0, (steps, batch))
        spikes, membranes, out_mem = _run_neuron(self.out_neuron, current, state.out,
                                                 keep_membrane=True)
        return spikes, cast(Tensor, membranes), ClassifierState(tuple(conv_mem), out_mem)

    def _stem(self, step: Tensor) -> Tensor:
        if self.stem is None:
            return step
        s = self.stem_stride
        pad_w, pad_h = -step.shape[-1] % s, -step.shape[-2] % s
        if pad_w or pad_h:
            step = functional.pad(step, (0, pad_w, 0, pad_h))
        return self.stem(step)

    def macs_per_step(self, height: int, width: int) -> int:
        """Multiply-accumulates of one time step of one sample of size ``height x width``.

        Counts the convolutions (stem and blocks, at their output sizes) and the linear layer;
        pooling and neurons are not counted.
        """
        h, w = check_positive_int("height", height), check_positive_int("width", width)
        macs = 0
        c_in = self.in_channels
        if self.stem is not None:
            h, w = -(-h // self.stem_stride), -(-w // self.stem_stride)
            macs += h * w * self.stem_channels * c_in * self.stem_stride**2
            c_in = self.stem_channels
        for c in self.channels:
            macs += h * w * c * c_in * 9
            h, w, c_in = -(-h // 2), -(-w // 2), c
        return macs + self.fc.in_features * self.fc.out_features

    @torch.no_grad()
    def predict(self, x: Tensor) -> Tensor:
        """Class of each sample: most output spikes, ties broken by the summed membrane.

        Args:
            x: ``[T, B, in_channels, H, W]`` input.

        Returns:
            ``[B]`` int64 class indices.
        """
        spikes, membrane, _ = self(x)
        return class_scores(spikes, membrane).argmax(1)


def class_scores(spikes: Tensor, membrane: Tensor) -> Tensor:
    """``[B, C]`` class scores: spike counts, ties broken by the summed membrane.

    The membrane term is squashed into ``(0, 1)``, so it orders classes only among those with
    equal spike counts.
    """
    return spikes.sum(0) + torch.sigmoid(membrane.sum(0))


def stem_stride_for(size: tuple[int, int], grid: int) -> int:
    """The stem stride that brings a ``(W, H)`` input to at most ``grid x grid``.

    Example:
        >>> stem_stride_for((128, 128), 16), stem_stride_for((16, 16), 16)
        (8, 1)
    """
    grid = check_positive_int("grid", grid)
    return max(1, -(-max(size) // grid))
