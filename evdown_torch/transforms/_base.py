"""The shape every downscaling transform shares."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import overload

import torch

from evdown_torch.checks import check_factor, check_positive_float, check_sensor_size, output_size
from evdown_torch.collate import EventBatch, from_batch, to_batch
from evdown_torch.events import Events, EventsLike, from_events, to_events
from evdown_torch.transforms.functional._reference import threshold_fraction


@dataclass(frozen=True)
class Downscaler:
    """Base of the downscaling transforms: settings, validation and the edge conversions.

    Subclasses are frozen dataclasses that implement :meth:`kernel`; ``__call__`` validates
    the events, converts them to :class:`~evdown_torch.events.Events`, calls the kernel and
    converts the result back to the caller's kind. Neither the input nor the transform is
    ever modified.

    Attributes:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``; pixel ``(x, y)`` goes to region
            ``(x // fx, y // fy)``.
    """

    sensor_size: tuple[int, int, int]
    factor: int | tuple[int, int] = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensor_size", check_sensor_size(self.sensor_size))
        check_factor(self.factor, self.sensor_size)

    @property
    def factor_xy(self) -> tuple[int, int]:
        """The factor as a pair ``(fx, fy)``."""
        return check_factor(self.factor)

    @property
    def output_sensor_size(self) -> tuple[int, int, int]:
        """Output sensor size ``(ceil(W / fx), ceil(H / fy), P)``, for the next transform."""
        return output_size(self.sensor_size, self.factor_xy)

    def kernel(self, events: Events) -> Events:  # pragma: no cover - abstract
        """Downscale validated events; implemented by each method."""
        raise NotImplementedError

    def __call__(self, events: EventsLike) -> EventsLike:
        """Downscale events of any accepted kind and return the same kind.

        Args:
            events: a Tonic structured array (fields x, y, t, p in any order), a tensor of
                shape ``(N, 4)`` with columns ``(x, y, t, p)``, or Events.

        Returns:
            The downscaled events, sorted by ``t``, in the input's kind, dtype and polarity
            encoding, with coordinates inside :attr:`output_sensor_size`.
        """
        ev, fmt = to_events(events, self.sensor_size)
        return from_events(self.kernel(ev), fmt)

    def batch_kernel(self, batch: EventBatch) -> EventBatch | None:
        """Downscale a batch of validated recordings in one pass.

        Methods run their kernel once on the recordings stacked on one virtual sensor
        (:func:`~evdown_torch.transforms._batch.run_stacked`), passing it each recording's
        stream bounds where the method needs them. The default, ``None``, means the method
        has no batched kernel: :meth:`batch` then processes the recordings one by one.
        """
        return None

    @overload
    def batch(self, recordings: EventBatch) -> EventBatch: ...

    @overload
    def batch(self, recordings: Sequence[EventsLike]) -> list[EventsLike]: ...

    def batch(self, recordings):
        """Downscale many recordings in one pass; each output equals the recording's own call.

        The recordings go through the kernel together (``docs/semantics.md``: processing
        several recordings in one batched call gives, for each, the same events as processing
        it alone), which costs much less than one call per recording when they are small.
        The frames mode of :class:`~evdown_torch.transforms.PhotocurrentPooling` has no
        batched kernel yet and processes the recordings one by one. The output limit
        (:func:`evdown_torch.set_max_output_events`, or ``LIFPooling.max_output_events``)
        applies to the batch as a whole.

        Args:
            recordings: a sequence of recordings of any accepted kind (on one device, all
                with integer or all with float timestamps), or an
                :class:`~evdown_torch.collate.EventBatch`.

        Returns:
            A list with each recording's output in its own kind, dtype and polarity encoding;
            an :class:`~evdown_torch.collate.EventBatch` (on the input's device) for an
            :class:`~evdown_torch.collate.EventBatch`.

        Example:
            >>> import torch
            >>> from evdown_torch import Downsample
            >>> down = Downsample((4, 4, 2), factor=2)
            >>> a, b = torch.tensor([[3, 1, 0, 1]]), torch.tensor([[2, 2, 5, 0], [0, 0, 6, 1]])
            >>> [out.tolist() for out in down.batch([a, b])]
            [[[1, 0, 0, 1]], [[1, 1, 5, 0], [0, 0, 6, 1]]]
        """
        if isinstance(recordings, EventBatch):
            events, _ = to_events(recordings.events, self.sensor_size)
            return self._batch_events(EventBatch(events, recordings.lengths))
        batch, formats = to_batch(recordings, self.sensor_size)
        return from_batch(self._batch_events(batch), formats)

    def _batch_events(self, batch: EventBatch) -> EventBatch:
        """:meth:`batch` on validated events."""
        out = self.batch_kernel(batch)
        if out is None:  # no batched kernel: one recording at a time
            parts = [self.kernel(part) for part in batch.unbind()]
            events = Events(*(torch.cat(columns) for columns in zip(*parts, strict=True)))
            out = EventBatch(events, tuple(part.num_events for part in parts))
        return out


@dataclass(frozen=True)
class ThresholdDownscaler(Downscaler):
    """Base of the log-luminance methods: a DVS reference rule at a contrast threshold.

    Attributes:
        threshold: contrast threshold on a region's mean level (in input events per pixel),
            > 0. It is used as the nearest fraction with denominator at most 10**6, so
            decimal thresholds such as 0.01 are exact.

    A call counts its output before building it and raises a ``ValueError`` naming the count
    when it would exceed :func:`evdown_torch.set_max_output_events` (100 million events by
    default): a threshold far below the level steps of a region asks for that many. The
    linear and cubic estimators also refuse integer timestamps spanning 2**53 or more, whose
    crossing times float64 cannot hold.
    """

    threshold: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "threshold", check_positive_float("threshold", self.threshold))
        threshold_fraction(self.threshold)
