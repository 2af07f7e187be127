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

:func:`optical_consistency` compares a downscaled stream with what a camera of the lower
resolution recorded (a reference stream on the same small sensor): both are counted per pixel,
polarity and short time bin (10 ms by default), and the score is ``1 - L1 / (n_a + n_b)``, one
minus the normalised L1 distance of the two count tensors. It lies in ``[0, 1]``: 1 for equal
counts everywhere, 0 when no bin holds events of both. Unlike a cosine it sees the rate: a
stream with every count doubled scores ``2/3``, thinned to half ``2/3`` too, so a method is
rewarded for events at the right place, polarity and time *and* in the right number.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evdown_torch._tensors import changes, ends, stable_sort_small, take, where_true
from evdown_torch.checks import check_positive_float, check_sensor_size
from evdown_torch.events import Events, EventsLike, to_events

__all__ = [
    "EventMetrics",
    "entropy",
    "event_metrics",
    "num_events",
    "optical_consistency",
    "temporal_density",
]


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


def _bin_keys(events: Events, w: int, h: int, bin_width: float, t_start: float,
              t_end: float) -> Tensor:
    t = events.t
    if t.dtype == torch.int64 and float(bin_width).is_integer() and float(t_start).is_integer():
        offset = t - int(t_start)
        index = torch.div(offset, int(bin_width), rounding_mode="floor")
    else:
        offset = t.to(torch.float64) - float(t_start)
        index = torch.floor(offset / float(bin_width)).to(torch.int64)
    inside = (offset >= 0) & (t <= t_end)
    index, p = index[inside], events.p[inside].to(torch.int64)
    return ((index * 2 + p) * h + events.y[inside]) * w + events.x[inside]


def optical_consistency(
    events: EventsLike,
    reference: EventsLike,
    sensor_size: tuple[int, int, int],
    *,
    bin_width: float = 10_000,
    t_start: float,
    t_end: float,
) -> float:
    """One minus the normalised L1 distance of two streams' binned counts.

    Both streams are counted per ``(time bin, polarity, y, x)``, bins of ``bin_width`` from
    ``t_start`` (events outside ``[t_start, t_end]`` are left out); with counts ``a`` and
    ``b``, the score is ``1 - sum |a - b| / (sum a + sum b)``. Only occupied bins are touched,
    so the cost follows the events, not the sensor area times the duration.

    Args:
        events: the stream to score (e.g. a downscaled recording).
        reference: the stream it should match (e.g. a low-resolution camera's recording).
        sensor_size: ``(W, H, P)`` of the sensor both live on.
        bin_width: bin length, in the streams' time unit (10 ms for microseconds), positive.
        t_start: the window's start, in the streams' time unit.
        t_end: the window's end (included).

    Returns:
        A score in ``[0, 1]``; 1 when both streams are empty in the window.

    Example:
        >>> import torch
        >>> ref = torch.tensor([[0, 0, 5, 1], [1, 0, 15, 1]])
        >>> doubled = torch.cat([ref, ref])
        >>> optical_consistency(doubled, ref, (2, 1, 2), bin_width=10, t_start=0, t_end=20)
        0.6666666666666667
        >>> optical_consistency(ref[:1], ref, (2, 1, 2), bin_width=10, t_start=0, t_end=20)
        0.6666666666666667
    """
    w, h, _ = check_sensor_size(sensor_size)
    bin_width = check_positive_float("bin_width", bin_width)
    if t_end < t_start:
        raise ValueError(f"t_end must not be before t_start, got {t_start} and {t_end}")
    a, _ = to_events(events, (w, h, 2))
    b, _ = to_events(reference, (w, h, 2))
    keys_a = _bin_keys(a, w, h, bin_width, t_start, t_end)
    keys_b = _bin_keys(b, w, h, bin_width, t_start, t_end).to(keys_a.device)
    total = keys_a.numel() + keys_b.numel()
    if total == 0:
        return 1.0
    # sort the bins of both streams together; each run of one bin sums +1 per event of
    # ``events`` and -1 per event of ``reference``: its absolute value is that bin's |a - b|
    keys, order = stable_sort_small(torch.cat([keys_a, keys_b]))
    running = torch.cumsum(torch.where(order < keys_a.numel(), 1, -1), 0)
    at_ends = take(running, where_true(ends(changes(keys))))
    per_bin = torch.diff(at_ends, prepend=at_ends.new_zeros(1))
    return 1.0 - float(per_bin.abs().sum()) / total
