"""Batches of recordings: one container, and collate functions for ``DataLoader``.

:class:`EventBatch` holds ``B`` recordings as one :class:`~evdown_torch.events.Events` stream
(the recordings concatenated) and their lengths; it moves between devices with ``.to``, and
every transform's :meth:`~evdown_torch.transforms.Downscaler.batch` downscales it in one pass
on the device it lives on. Two collate functions build it inside a ``DataLoader``:

* :class:`EventsCollate` collates ``(events, target)`` samples into ``(EventBatch, targets)``,
  so that the training loop moves the batch to the GPU and downscales it there;
* :class:`DownscaleCollate` downscales the collated batch right away (in the loader's
  workers), optionally applies a per-recording transform such as Tonic's ``ToFrame`` to each
  output, and hands the results to a collate function such as Tonic's ``PadTensors``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import default_collate

from evdown_torch.events import (
    EventFormat,
    Events,
    EventsLike,
    _polarity_encoding,
    _warn_if_time_lost_precision,
    from_events,
    to_events,
)

__all__ = ["DownscaleCollate", "EventBatch", "EventsCollate", "from_batch", "to_batch"]


@dataclass(frozen=True)
class EventBatch:
    """``B`` recordings as one stream: their events concatenated and their lengths.

    Attributes:
        events: the recordings' :class:`~evdown_torch.events.Events` concatenated, recording 0
            first (``N = sum(lengths)`` events on one device).
        lengths: number of events of each recording.

    Example:
        >>> import torch
        >>> batch = EventBatch.from_recordings(
        ...     [torch.tensor([[0, 0, 5, 1]]), torch.zeros((0, 4), dtype=torch.int64)])
        >>> batch.lengths, [r.t.tolist() for r in batch.unbind()]
        ((1, 0), [[5], []])
    """

    events: Events
    lengths: tuple[int, ...]

    def __post_init__(self) -> None:
        lengths = tuple(int(n) for n in self.lengths)
        if any(n < 0 for n in lengths) or sum(lengths) != self.events.num_events:
            raise ValueError(
                f"EventBatch lengths must be non-negative and add up to the number of events "
                f"({self.events.num_events}), got {sum(lengths)} from {len(lengths)} recordings"
            )
        object.__setattr__(self, "lengths", lengths)

    @staticmethod
    def from_recordings(
        recordings: Sequence[EventsLike], sensor_size: tuple[int, int, int] | None = None
    ) -> EventBatch:
        """Validate and concatenate recordings of any accepted kind (see :func:`to_batch`)."""
        return to_batch(recordings, sensor_size)[0]

    @property
    def num_recordings(self) -> int:
        """Number of recordings ``B``."""
        return len(self.lengths)

    @property
    def device(self) -> torch.device:
        """Device the events live on."""
        return self.events.device

    def to(self, device: torch.device | str, non_blocking: bool = False) -> EventBatch:
        """The same batch on ``device``."""
        events = Events(*(c.to(device, non_blocking=non_blocking) for c in self.events))
        return EventBatch(events, self.lengths)

    def unbind(self) -> list[Events]:
        """Each recording's events (views of the batch's tensors)."""
        return [Events(*parts) for parts in zip(*(c.split(self.lengths) for c in self.events))]


def _check_one_device_and_clock(parts: list[Events]) -> None:
    devices = {e.device for e in parts}
    if len(devices) > 1:
        raise ValueError(f"the recordings of a batch must be on one device, got {devices}")
    kinds = {e.t.is_floating_point() for e in parts}
    if len(kinds) > 1:
        raise ValueError(
            "the recordings of a batch must all have integer or all float timestamps; "
            "got both (convert them to one timestamp dtype first)"
        )


def _structured_columns(
    recordings: list[np.ndarray], sensor_size: tuple[int, int, int] | None
) -> tuple[Events, EventFormat]:
    """Structured arrays of one dtype, converted field by field straight into one stream.

    Much faster than concatenating the structured arrays first.
    """
    _, fmt = to_events(recordings[0][:0])  # checks the fields and their dtypes
    t_kind = recordings[0].dtype["t"]
    t_dtype = np.float64 if np.issubdtype(t_kind, np.floating) else np.int64
    x, y, t = (torch.from_numpy(np.concatenate([r[f] for r in recordings], dtype=dtype))
               for f, dtype in (("x", np.int64), ("y", np.int64), ("t", t_dtype)))
    _warn_if_time_lost_precision(t, t_kind.name)
    p = torch.from_numpy(np.concatenate([r["p"] for r in recordings]))
    if p.dtype != torch.bool:
        fmt = EventFormat(fmt.kind, fmt.dtype, _polarity_encoding(p), fmt.device)
        p = p > 0
    events, _ = to_events(Events(x, y, t, p), sensor_size)
    return events, fmt


def _concatenated(
    recordings: list[EventsLike], sensor_size: tuple[int, int, int] | None
) -> tuple[Events, EventFormat] | None:
    """The recordings as one stream, when they share kind and dtype (else ``None``)."""
    first = recordings[0]
    if isinstance(first, np.ndarray) and first.dtype.names is not None:
        arrays = [r for r in recordings
                  if isinstance(r, np.ndarray) and r.dtype == first.dtype and r.ndim == 1]
        if len(arrays) == len(recordings):
            return _structured_columns(arrays, sensor_size)
    if isinstance(first, Tensor):
        tensors = [r for r in recordings
                   if isinstance(r, Tensor) and r.dtype == first.dtype
                   and r.device == first.device and r.ndim == 2
                   and r.shape[1:] == first.shape[1:]]
        if len(tensors) == len(recordings):
            return to_events(torch.cat(tensors), sensor_size)
    return None


def to_batch(
    recordings: Sequence[EventsLike], sensor_size: tuple[int, int, int] | None = None
) -> tuple[EventBatch, list[EventFormat]]:
    """Validate recordings of any accepted kind and concatenate them into an :class:`EventBatch`.

    Recordings of one kind and dtype (the usual case) are converted in one pass; each keeps
    its own :class:`~evdown_torch.events.EventFormat` (its polarity encoding included), so
    :func:`from_batch` gives each output back exactly as a single call would.

    Args:
        recordings: Tonic structured arrays, ``(N, 4)`` tensors or Events, on one device, all
            with integer or all with float timestamps.
        sensor_size: ``(W, H, P)``; when given, coordinates must lie inside it.

    Returns:
        The batch and each recording's format.

    Raises:
        TypeError, ValueError: as :func:`~evdown_torch.events.to_events` for any recording
            (the message names it), or for recordings on several devices or with both
            integer and float timestamps.
    """
    recordings = list(recordings)
    if not recordings:
        raise ValueError("a batch needs at least one recording, got none")
    lengths = tuple(_length(r) for r in recordings)
    try:
        whole = _concatenated(recordings, sensor_size)
    except (TypeError, ValueError):
        whole = None  # one by one below: the message names the recording
    if whole is not None:
        events, fmt = whole
        if fmt.polarity != "signed":
            return EventBatch(events, lengths), [fmt] * len(recordings)
        # Signed overall: a recording without an OFF event reads as 0/1 on its own.
        batch = EventBatch(events, lengths)
        off = [bool((~part.p).any()) for part in batch.unbind()]
        binary = EventFormat(fmt.kind, fmt.dtype, "binary", fmt.device)
        return batch, [fmt if has_off else binary for has_off in off]
    parts, formats = [], []
    for i, recording in enumerate(recordings):
        try:
            events, fmt = to_events(recording, sensor_size)
        except (TypeError, ValueError) as error:
            raise type(error)(f"recording {i} of the batch: {error}") from None
        parts.append(events)
        formats.append(fmt)
    _check_one_device_and_clock(parts)
    events = Events.cat(parts)
    return EventBatch(events, lengths), formats


def _length(recording: EventsLike) -> int:
    if isinstance(recording, Events):
        return recording.num_events
    if isinstance(recording, (np.ndarray, Tensor)) and recording.ndim >= 1:
        return int(recording.shape[0])
    return 0  # to_events names the problem


def from_batch(batch: EventBatch, formats: Sequence[EventFormat]) -> list[EventsLike]:
    """Each recording of ``batch`` in its own format (the inverse of :func:`to_batch`)."""
    if len(set(formats)) == 1:  # one conversion, then split
        whole = from_events(batch.events, formats[0])
        if isinstance(whole, np.ndarray):
            return list(np.split(whole, np.cumsum(batch.lengths)[:-1]))
        if isinstance(whole, Tensor):
            return list(whole.split(batch.lengths))
    return [from_events(part, fmt) for part, fmt in zip(batch.unbind(), formats, strict=True)]


def apply_item_transforms(dataset: Any, events: Any, target: Any) -> tuple[Any, Any]:
    """One dataset item after the dataset's Tonic-style transforms.

    Args:
        dataset: has ``transform`` (applied to the events), ``target_transform`` (to the
            target) and ``transforms`` (to both, last); each may be None.
        events: the item's events.
        target: the item's label.

    Returns:
        ``(events, target)`` after the transforms that are set.
    """
    if dataset.transform is not None:
        events = dataset.transform(events)
    if dataset.target_transform is not None:
        target = dataset.target_transform(target)
    if dataset.transforms is not None:
        events, target = dataset.transforms(events, target)
    return events, target


def _split_samples(samples: Sequence[Any]) -> tuple[list[EventsLike], list[Any] | None]:
    if all(isinstance(s, tuple) and not isinstance(s, Events) and len(s) == 2 for s in samples):
        return [s[0] for s in samples], [s[1] for s in samples]
    return list(samples), None


@dataclass(frozen=True)
class EventsCollate:
    """Collate ``(events, target)`` samples (or bare events) into an :class:`EventBatch`.

    Use it as a ``DataLoader``'s ``collate_fn`` to downscale on the training device:
    ``batch, targets = next(iter(loader)); down.batch(batch.to("cuda"))``.

    Attributes:
        sensor_size: when given, coordinates must lie inside it.

    Returns (when called):
        ``(EventBatch, targets)`` with targets collated by ``default_collate``, or the
        :class:`EventBatch` alone for bare events.

    Example:
        >>> import torch
        >>> samples = [(torch.tensor([[0, 0, 5, 1]]), 3), (torch.tensor([[1, 1, 6, 0]]), 4)]
        >>> batch, targets = EventsCollate()(samples)
        >>> batch.lengths, targets.tolist()
        ((1, 1), [3, 4])
    """

    sensor_size: tuple[int, int, int] | None = None

    def __call__(self, samples: Sequence[Any]) -> tuple[EventBatch, Any] | EventBatch:
        """Collate ``(recording, target)`` samples (or bare recordings) into one batch."""
        recordings, targets = _split_samples(samples)
        batch = EventBatch.from_recordings(recordings, self.sensor_size)
        return batch if targets is None else (batch, default_collate(targets))


@dataclass(frozen=True)
class DownscaleCollate:
    """A ``collate_fn`` that downscales a whole batch of recordings in one pass.

    Each sample is ``(events, target)`` (or bare events); the events of the batch go through
    ``transform.batch`` at once, each output optionally through ``per_sample`` (for example
    ``tonic.transforms.ToFrame(sensor_size=down.output_sensor_size, n_time_bins=10)``), and
    the resulting ``(output, target)`` pairs through ``collate`` (for example
    ``tonic.collation.PadTensors(batch_first=True)``; by default each output is kept in a list
    and the targets collated by ``default_collate``).

    Attributes:
        transform: a downscaler (anything with a ``batch(list_of_recordings)`` method).
        per_sample: optional transform of each downscaled recording.
        collate: optional collate function of the ``(output, target)`` pairs.

    Example:
        >>> import torch
        >>> from evdown_torch import Downsample
        >>> collate = DownscaleCollate(Downsample((4, 4, 2), factor=2))
        >>> outputs, targets = collate([(torch.tensor([[3, 3, 5, 1]]), 0),
        ...                             (torch.tensor([[1, 2, 6, 0]]), 1)])
        >>> [o.tolist() for o in outputs], targets.tolist()
        ([[[1, 1, 5, 1]], [[0, 1, 6, 0]]], [0, 1])
    """

    transform: Any
    per_sample: Callable[[EventsLike], Any] | None = None
    collate: Callable[[list[Any]], Any] | None = None

    def __call__(self, samples: Sequence[Any]) -> Any:
        """Downscale the samples' recordings as one batch, then collate them as configured."""
        recordings, targets = _split_samples(samples)
        outputs = self.transform.batch(recordings)
        if self.per_sample is not None:
            outputs = [self.per_sample(out) for out in outputs]
        if self.collate is not None:
            if targets is None:
                return self.collate(outputs)
            return self.collate(list(zip(outputs, targets, strict=True)))
        return outputs if targets is None else (outputs, default_collate(targets))
