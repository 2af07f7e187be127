"""A plain training and evaluation loop for :class:`~evdown_torch.models.SpikingClassifier`.

The loops take any ``torch.utils.data.DataLoader`` whose batches are ``(frames, labels)`` with
``frames`` of shape ``[B, T, 2, H, W]`` (what a DataLoader stacks from samples of
``[T, 2, H, W]``, e.g. :func:`evdown_torch.frames.to_frames` or
``tonic.transforms.ToFrame(sensor_size, n_time_bins=T)``, any numeric dtype) and ``labels``
of shape ``[B]``. They move each batch to the model's device and feed it time-first, integer
frames as float32 and floating ones in their own dtype (the classifier copies its input into
its parameters' dtype once).

Example, on DVS128 Gesture (needs tonic and the dataset on disk)::

    import tonic, torch
    from torch.utils.data import DataLoader
    from evdown_torch import EventCount
    from evdown_torch.models import SpikingClassifier
    from evdown_torch.models.training import evaluate_classifier, train_classifier

    down = EventCount(tonic.datasets.DVSGesture.sensor_size, factor=4)
    frames = tonic.transforms.ToFrame(down.output_sensor_size, n_time_bins=16)
    transform = tonic.transforms.Compose([down, frames])
    train = tonic.datasets.DVSGesture("data", train=True, transform=transform)
    test = tonic.datasets.DVSGesture("data", train=False, transform=transform)
    order = torch.Generator().manual_seed(0)
    model = SpikingClassifier(num_classes=11)
    train_classifier(model, DataLoader(train, 16, shuffle=True, generator=order), epochs=10)
    print(evaluate_classifier(model, DataLoader(test, 16)))
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable

import snntorch.functional
import torch
from torch import Tensor, nn

from evdown_torch.checks import check_positive_float, check_positive_int
from evdown_torch.models.classifier import class_scores

__all__ = ["evaluate_classifier", "predict_classifier", "train_classifier"]

Batches = Iterable[tuple[Tensor, Tensor]]


def _time_first(frames: Tensor, device: torch.device) -> Tensor:
    if frames.ndim != 5:
        raise ValueError(
            f"a batch of frames must have shape [B, T, 2, H, W], got {tuple(frames.shape)}"
        )
    # A floating batch goes as it is: the model copies it once into its own dtype (a
    # conversion here would allocate and fill a second batch-sized tensor).
    dtype = frames.dtype if frames.dtype.is_floating_point else torch.float32
    return frames.to(device=device, dtype=dtype).transpose(0, 1)


def _device_of(model: nn.Module) -> torch.device:
    parameter = next(model.parameters(), None)
    return parameter.device if parameter is not None else torch.device("cpu")


def train_classifier(
    model: nn.Module,
    loader: Batches,
    *,
    epochs: int,
    learning_rate: float = 5e-3,
    loss_fn: Callable[[Tensor, Tensor], Tensor] | None = None,
    log: Callable[[str], None] | None = None,
) -> list[float]:
    """Train a spiking classifier with Adam and a snntorch loss on its output spikes.

    The loss is snntorch's spike-count mean-square error,
    ``snntorch.functional.mse_count_loss(correct_rate=0.8, incorrect_rate=0.2)`` (the correct
    class is pushed to fire on 80% of the time steps, the others on 20%), unless ``loss_fn``
    says otherwise; on synthetic gestures it trains markedly better than the cross-entropy
    spike-rate loss, which plateaus below 80%. Training is
    deterministic when the loader's order is (a DataLoader with a seeded ``generator``) and the
    model was initialised under a fixed seed; the loop itself draws no random numbers.

    Args:
        model: a module mapping ``[T, B, 2, H, W]`` to ``(spikes, membrane, state)`` with
            ``spikes`` and ``membrane`` of shape ``[T, B, C]``, e.g. SpikingClassifier; trained
            in place on the device it lives on.
        loader: batches ``(frames [B, T, 2, H, W], labels [B])``.
        epochs: passes over the loader.
        learning_rate: Adam's step size.
        loss_fn: ``loss_fn(spikes [T, B, C], labels [B])`` returning a scalar tensor, e.g.
            ``snntorch.functional.ce_count_loss()``; default ``mse_count_loss`` as above.
        log: called with one line per epoch (loss and elapsed seconds), if given.

    Returns:
        The mean loss of each epoch.

    Example:
        >>> import torch
        >>> from evdown_torch.models import SpikingClassifier
        >>> g = torch.Generator().manual_seed(0)
        >>> x, y = torch.rand(8, 4, 2, 6, 6, generator=g), torch.arange(8) % 2
        >>> net = SpikingClassifier(num_classes=2, channels=(4,), pool_size=1)
        >>> losses = train_classifier(net, [(x, y)], epochs=2)
        >>> len(losses), evaluate_classifier(net, [(x, y)]) <= 1.0
        (2, True)
    """
    epochs = check_positive_int("epochs", epochs)
    learning_rate = check_positive_float("learning_rate", learning_rate)
    device = _device_of(model)
    optimiser = torch.optim.Adam(model.parameters(), lr=learning_rate)
    if loss_fn is None:
        loss_fn = snntorch.functional.mse_count_loss(correct_rate=0.8, incorrect_rate=0.2)
    model.train()
    losses = []
    start = time.perf_counter()
    for epoch in range(epochs):
        total, count = 0.0, 0
        for frames, labels in loader:
            x = _time_first(frames, device)
            target = labels.to(device=device, dtype=torch.int64)
            spikes, _, _ = model(x)
            loss = loss_fn(spikes, target)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            total += float(loss.detach()) * target.shape[0]
            count += target.shape[0]
        if count == 0:
            raise ValueError("the training loader yielded no samples")
        losses.append(total / count)
        if log is not None:
            log(f"epoch {epoch + 1}/{epochs}: loss {losses[-1]:.4f}, "
                f"{time.perf_counter() - start:.1f} s")
    return losses


@torch.no_grad()
def evaluate_classifier(model: nn.Module, loader: Batches) -> float:
    """Accuracy of a spiking classifier, in ``[0, 1]``.

    A sample's class is the output neuron with the most spikes, ties broken by the summed
    output membrane (``evdown_torch.models.classifier.class_scores``).

    Args:
        model: as for :func:`train_classifier`.
        loader: batches ``(frames [B, T, 2, H, W], labels [B])``.

    Returns:
        The fraction of samples classified correctly.

    Raises:
        ValueError: if the loader yields no samples.
    """
    predicted, labels = predict_classifier(model, loader)
    return float((predicted == labels).to(torch.float64).mean())


@torch.no_grad()
def predict_classifier(model: nn.Module, loader: Batches) -> tuple[Tensor, Tensor]:
    """The class a spiking classifier gives each sample, and the sample's label.

    Args:
        model: as for :func:`train_classifier`.
        loader: batches ``(frames [B, T, 2, H, W], labels [B])``, in the order wanted.

    Returns:
        ``(predicted, labels)``: two ``[N]`` int64 CPU tensors, in the loader's order.

    Raises:
        ValueError: if the loader yields no samples.
    """
    device = _device_of(model)
    model.eval()
    predicted, truth = [], []
    for frames, labels in loader:
        spikes, membrane, _ = model(_time_first(frames, device))
        predicted.append(class_scores(spikes, membrane).argmax(1).cpu())
        truth.append(labels.to(torch.int64).cpu())
    if not predicted:
        raise ValueError("the evaluation loader yielded no samples")
    return torch.cat(predicted), torch.cat(truth)
