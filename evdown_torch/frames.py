"""Event-to-frame binning: a stream becomes ``[T, 2, H, W]`` event-count frames.

Like ``tonic.transforms.ToFrame(n_time_bins=T)`` (channel order OFF then ON), with one shape
and one dtype for every input, empty or not, and an explicit time window, so that a stream and
its downscaled versions are binned over the same window.

The window ``[t_start, t_end]`` (by default the smallest and largest ``t`` of the stream) is
cut into ``T`` bins of equal length ``D / T``, ``D = t_end - t_start``: an event at ``t`` goes
to bin ``floor((t - t_start) * T / D)``, the last bin also holding ``t_end`` itself. The index
is computed exactly for integer timestamps (int64 arithmetic relative to ``t_start``, or, for
spans whose ``D * T`` leaves int64, against the exact bin edges ``t_start + ceil(k D / T)``).
Events outside the window are left out. A window of zero length puts every event in bin 0.

With ``mean_time=True`` two more channels say *when* in its bin each pixel fired: the mean
position of its OFF (channel 2) and ON (channel 3) events within the bin, from -1 at the bin's
start to +1 at its end, and 0 where the pixel has no event of that polarity. Counts alone lose
the order of events within a bin (an arm sweeping one way or the other leaves the same counts);
the mean time keeps the direction of motion at little cost, like the timestamp channels of
event-based optical-flow and recognition networks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from evdown_torch.checks import check_finite_number, check_positive_int, check_sensor_size
from evdown_torch.events import EventsLike, to_events

__all__ = ["ToFrames", "to_frames"]

_INT64 = torch.iinfo(torch.int64)


def _window_bound(name: str, value: object) -> int | float | None:
    """``t_start`` or ``t_end`` checked: ``None``, or a finite number (an int within int64)."""
    if value is None:
        return None
    if isinstance(value, Tensor) and value.numel() == 1:
        value = value.item()
    bound = check_finite_number(name, value)
    if isinstance(bound, int) and not _INT64.min <= bound <= _INT64.max:
        raise ValueError(f"{name} must lie in int64's range (as the timestamps), got {bound}")
    return bound


def _int_bins(t: Tensor, start: int, span: int, bins: int,
              mean_time: bool) -> tuple[Tensor, Tensor | None]:
    """Each integer ``t``'s bin index (and position in it, with ``mean_time``), exactly.

    Only the values of ``t`` inside the window ``[start, start + span]`` are meaningful.
    """
    if span * bins <= _INT64.max:  # (t - start) * bins holds in int64 inside the window
        offset = t - start
        if span == 0:
            return torch.zeros_like(offset), (torch.zeros_like(offset, dtype=torch.float64)
                                              if mean_time else None)
        scaled = offset * bins
        index = scaled // span
        # position within the bin, exactly in [0, 1): (offset * T - index * D) / D
        within = (scaled - index * span).to(torch.float64) / span if mean_time else None
        return index, within
    # A span too long for int64 arithmetic: count the exact bin edges at or below each t.
    edges = torch.tensor([start + -(-k * span // bins) for k in range(1, bins)],
                         dtype=torch.int64, device=t.device)
    index = torch.searchsorted(edges, t, right=True)
    if not mean_time:
        return index, None
    within = ((t.to(torch.float64) - float(start)) * (bins / span) - index).clamp_(0.0, 1.0)
    return index, within


def to_frames(
    events: EventsLike,
    sensor_size: tuple[int, int, int],
    n_time_bins: int,
    *,
    t_start: float | None = None,
    t_end: float | None = None,
    mean_time: bool = False,
) -> Tensor:
    """Count events per time bin, polarity and pixel.

    Args:
        events: a Tonic structured array, an ``(N, 4)`` tensor ``(x, y, t, p)`` or Events.
        sensor_size: ``(W, H, P)`` of the sensor the events live on (``P`` is 1 or 2; the
            frames always have two channels, OFF then ON, by each event's polarity).
        n_time_bins: number of bins ``T``.
        t_start: start of the window, in the stream's time unit; default: the smallest ``t``.
        t_end: end of the window (included); default: the largest ``t``.
        mean_time: also return each bin's mean event time per pixel and polarity (module
            docstring).

    Returns:
        ``[T, 2, H, W]`` float32 event counts on the events' device (channel 0 OFF, 1 ON),
        or ``[T, 4, H, W]`` with ``mean_time`` (channels 2 and 3: the OFF and ON events' mean
        position in their bin, in ``[-1, 1]``); all zeros for an empty stream.

    Raises:
        ValueError: for ``t_end < t_start``, a bound that is not finite (or an integer outside
            int64), a bad ``n_time_bins`` or invalid events.
        TypeError: for a bound that is not a number.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 0, 1], [1, 0, 5, 0], [1, 0, 10, 1]])
        >>> frames = to_frames(ev, (2, 1, 2), n_time_bins=2)
        >>> frames.shape, frames[:, 1, 0].tolist(), frames[:, 0, 0].tolist()
        (torch.Size([2, 2, 1, 2]), [[1.0, 0.0], [0.0, 1.0]], [[0.0, 0.0], [0.0, 1.0]])
        >>> timed = to_frames(ev, (2, 1, 2), n_time_bins=2, mean_time=True)
        >>> timed.shape, timed[0, 3, 0].tolist(), timed[1, :, 0, 1].tolist()
        (torch.Size([2, 4, 1, 2]), [-1.0, 0.0], [1.0, 1.0, -1.0, 1.0])
    """
    w, h, _ = check_sensor_size(sensor_size)
    bins = check_positive_int("n_time_bins", n_time_bins)
    t_start, t_end = _window_bound("t_start", t_start), _window_bound("t_end", t_end)
    ev, _ = to_events(events, (w, h, 2))
    size = bins * 2 * h * w
    channels = 4 if mean_time else 2
    if ev.num_events == 0:
        return torch.zeros(bins, channels, h, w, dtype=torch.float32, device=ev.device)
    t = ev.t
    if t.dtype == torch.int64 and not (isinstance(t_start, float) or isinstance(t_end, float)):
        start_int = int(t.min()) if t_start is None else int(t_start)
        end_int = int(t.max()) if t_end is None else int(t_end)
        if end_int < start_int:  # Python ints: no span overflows
            raise ValueError(f"t_end must not be before t_start, got {start_int} and {end_int}")
        index, within = _int_bins(t, start_int, end_int - start_int, bins, mean_time)
        inside = (t >= start_int) & (t <= end_int)  # no t - t_start, which may wrap
    else:
        start = t.min() if t_start is None else torch.as_tensor(t_start, device=t.device)
        end = t.max() if t_end is None else torch.as_tensor(t_end, device=t.device)
        t = t.to(torch.float64)
        start, end = start.to(torch.float64), end.to(torch.float64)
        span = end - start
        if float(span) < 0:
            raise ValueError(
                f"t_end must not be before t_start, got {float(start)} and {float(end)}"
            )
        offset = t - start
        scaled = offset * bins / span if float(span) > 0 else torch.zeros_like(offset)
        index = torch.floor(scaled).to(torch.int64)
        within = scaled - index if mean_time else None
        inside = (offset >= 0) & (t <= end)
    if within is not None:  # t_end itself (index T) belongs to the last bin, at its end
        within = torch.where(index >= bins, 1.0, within)[inside]
    index = index.clamp(max=bins - 1)[inside]
    flat = ((index * 2 + ev.p[inside].to(torch.int64)) * h + ev.y[inside]) * w + ev.x[inside]
    counts = torch.bincount(flat, minlength=size)
    frames = counts.to(torch.float32).reshape(bins, 2, h, w)
    if within is None:  # no mean_time
        return frames
    total = torch.bincount(flat, weights=within * 2 - 1, minlength=size)
    mean = (total / counts.clamp(min=1)).to(torch.float32).reshape(bins, 2, h, w)
    return torch.cat([frames, mean], dim=1)


@dataclass(frozen=True)
class ToFrames:
    """:func:`to_frames` as a Tonic transform.

    In place of ``tonic.transforms.ToFrame`` (with ``n_time_bins``), with one shape for every
    stream, empty ones included.

    A downscaler with a high threshold can leave a recording with no events, and Tonic then
    breaks a ``DataLoader`` mid-epoch: ``tonic.transforms.Compose`` stops at the first empty
    output, skipping ``ToFrame``, and ``tonic.collation.PadTensors`` cannot stack the empty
    event array with the other samples' frames ("stack expects each tensor to be equal size"
    or "can't convert np.ndarray of type numpy.void"). So give the downscaler to this
    transform as ``transform``, instead of composing the two with Tonic's ``Compose``: it
    always frames, and an empty stream gives zeros of the right shape.

    Args:
        sensor_size: ``(W, H, P)`` of the events it frames (a downscaler's
            ``output_sensor_size``).
        n_time_bins: number of bins ``T`` over each stream's own first to last timestamp.
        mean_time: add the mean-time channels (see :func:`to_frames`).
        transform: applied to the events first (a downscaler, a ``Chain``, or any callable
            returning events, even empty ones); ``None``: frame the events as they come.

    Returns (when called):
        ``[T, 2, H, W]`` (``[T, 4, H, W]`` with ``mean_time``) float32 frames, zeros for an
        empty stream.

    Example:
        >>> import numpy as np
        >>> from evdown_torch import EventCount
        >>> from evdown_torch.events import DVS_DTYPE
        >>> down = EventCount((8, 6, 2), factor=2, threshold=100.0)  # nothing gets through
        >>> to_frames_ = ToFrames(down.output_sensor_size, n_time_bins=5, transform=down)
        >>> to_frames_(np.zeros(3, DVS_DTYPE)).shape  # a Tonic dataset's transform=
        torch.Size([5, 2, 3, 4])
    """

    sensor_size: tuple[int, int, int]
    n_time_bins: int
    mean_time: bool = False
    transform: Callable[[EventsLike], EventsLike] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensor_size", check_sensor_size(self.sensor_size))
        check_positive_int("n_time_bins", self.n_time_bins)
        if not isinstance(self.mean_time, bool):
            raise TypeError(f"mean_time must be a bool, got {self.mean_time!r}")
        if self.transform is not None and not callable(self.transform):
            raise TypeError(f"transform must be callable, got {self.transform!r}")

    def __call__(self, events: EventsLike) -> Tensor:
        """Apply ``transform`` (if any), then frame: ``[T, 2 or 4, H, W]`` float32."""
        if self.transform is not None:
            events = self.transform(events)
        return to_frames(events, self.sensor_size, self.n_time_bins, mean_time=self.mean_time)
