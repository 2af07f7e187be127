"""The paper's event-stream metrics: number of events, temporal density, information entropy.

Following Gruel et al. (VISAPP 2022), equations 5 to 7, for a stream on a ``W x H`` sensor
lasting ``D = t_max - t_min`` time units (microseconds for Tonic datasets):

* the activation probability of a pixel is ``a(x, y) = (events at the pixel) / D``, the chance
  that the pixel fires in one time unit (per microsecond for Tonic datasets), and
  ``a_s(x, y)`` the same count restricted to polarity ``s`` (ON or OFF);
* the **temporal density** is the mean of ``a`` over the ``W * H`` pixels, in events per
  pixel per time unit;
* the **information entropy** is the mean over the ``W * H`` pixels and both polarities of the
  binary entropy ``-a_s log2 a_s - (1 - a_s) log2 (1 - a_s)``, in bits. A probability cannot
  exceed 1: a pixel with more events of one polarity than time units in ``D`` (bursts at one
  timestamp) counts as ``a_s = 1``, whose entropy is 0.

Pass ``duration=`` to measure a downscaled stream over the duration of its source, so that
streams of one recording are compared over one time window.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evdown_torch.checks import check_positive_float, check_sensor_size
from evdown_torch.events import Events, EventsLike, to_events

__all__ = ["EventMetrics", "entropy", "event_metrics", "num_events", "temporal_density"]


@dataclass(frozen=True)
class EventMetrics:
    """The three metrics of one stream.

    Attributes:
        num_events: number of events.
        density: temporal density, events per pixel per time unit.
        entropy: mean binary entropy per pixel and polarity, bits.
    """

    num_events: int
    density: float
    entropy: float


def _duration(events: Events, duration: float | None) -> float:
    if duration is not None:
        return check_positive_float("duration", duration)
    span = float(events.t.max() - events.t.min())
    if span <= 0:
        raise ValueError(
            "the stream spans no time (all events share one timestamp); pass duration= to "
            "say over how long it was recorded"
        )
    return span


def _counts(events: Events, sensor_size: tuple[int, int, int]) -> Tensor:
    """``(2, H, W)`` float64 counts, OFF then ON."""
    w, h, _ = sensor_size
    index = (events.p.to(torch.int64) * h + events.y) * w + events.x
    counts = torch.bincount(index, minlength=2 * h * w)
    return counts.to(torch.float64).reshape(2, h, w)


def num_events(events: EventsLike) -> int:
    """Number of events of a stream of any accepted kind.

    Example:
        >>> import torch
        >>> num_events(torch.tensor([[0, 0, 1, 1], [1, 0, 2, 0]]))
        2
    """
    return to_events(events)[0].num_events


def event_metrics(
    events: EventsLike, sensor_size: tuple[int, int, int], *, duration: float | None = None
) -> EventMetrics:
    """Number of events, temporal density and entropy of a stream.

    Args:
        events: a Tonic structured array, an ``(N, 4)`` tensor ``(x, y, t, p)`` or Events.
        sensor_size: ``(W, H, P)`` of the sensor the events live on.
        duration: the time window ``D`` in the stream's time unit; by default
            ``t_max - t_min`` of the events.

    Returns:
        The :class:`EventMetrics`; an empty stream has density and entropy 0.

    Raises:
        ValueError: when the stream spans no time and no ``duration`` is given, or for
            invalid events.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 0, 1], [1, 0, 10, 1], [1, 0, 10, 0]])
        >>> m = event_metrics(ev, (2, 1, 2))
        >>> m.num_events, m.density
        (3, 0.15)
    """
    sensor_size = check_sensor_size(sensor_size)
    ev, _ = to_events(events, sensor_size)
    if ev.num_events == 0:
        if duration is not None:
            check_positive_float("duration", duration)
        return EventMetrics(0, 0.0, 0.0)
    d = _duration(ev, duration)
    counts = _counts(ev, sensor_size)
    density = float(counts.sum(0).mean() / d)
    a = (counts / d).clamp(max=1.0)
    bits = -(torch.special.xlogy(a, a) + torch.special.xlogy(1 - a, 1 - a)) / torch.log(
        torch.tensor(2.0, dtype=torch.float64)
    )
    return EventMetrics(ev.num_events, density, float(bits.mean()))


def temporal_density(
    events: EventsLike, sensor_size: tuple[int, int, int], *, duration: float | None = None
) -> float:
    """Mean activation probability over the ``W * H`` pixels (events per pixel per time unit).

    See :func:`event_metrics` for the arguments.
    """
    return event_metrics(events, sensor_size, duration=duration).density


def entropy(
    events: EventsLike, sensor_size: tuple[int, int, int], *, duration: float | None = None
) -> float:
    """Mean binary entropy (bits) of the per-polarity activation probabilities.

    See :func:`event_metrics` for the arguments.
    """
    return event_metrics(events, sensor_size, duration=duration).entropy
