"""Event rates in windows of a fixed length: the mean, the 99th percentile and the peak.

A chip that takes at most ``R`` events per window of ``W`` cares about the peak, not the
mean: a recording at the right mean rate can hold twice as many events in its busiest
millisecond. :func:`window_rates` measures both (docs/choosing.md, "Mean and peak"), and
:func:`peak_count` is the measure a peak budget (``BudgetTarget.peak``) calibrates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from evdown_torch._tensors import searchsorted_ascending
from evdown_torch.checks import DEFAULT_TIME_UNIT, check_positive_float, check_time_unit
from evdown_torch.events import EventsLike, to_events

__all__ = ["WindowRates", "peak_count", "window_rates"]


def peak_count(t: Tensor, window: float) -> int:
    """The most events in any window ``[s, s + window)``, for sorted timestamps ``t``.

    The busiest window starts at an event, so this is
    ``max_i #{j : t_i <= t_j < t_i + window}``: one sorted search per event.

    Args:
        t: ``(N,)`` int64 or float64 timestamps, ascending.
        window: the window's length in ``t``'s unit, > 0.

    Example:
        >>> peak_count(torch.tensor([0, 1, 2, 10, 10, 11, 19]), 10)  # [10, 20)
        4
    """
    if t.shape[0] == 0:
        return 0
    if t.is_floating_point() or not float(window).is_integer():
        t = t.to(torch.float64)
        end = t + float(window)
    else:  # exact for integer timestamps
        end = t + int(window)
    inside = searchsorted_ascending(t, end) - torch.arange(t.shape[0], device=t.device)
    return int(inside.max())


def _window_counts(t: Tensor, window: float) -> np.ndarray:
    """Events in each consecutive window ``[t_0 + k W, t_0 + (k + 1) W)`` up to the last event."""
    offset = t - t[0]
    if t.is_floating_point() or not float(window).is_integer():
        index = torch.floor(offset.to(torch.float64) / window).to(torch.int64)
    else:  # exact for integer timestamps
        index = torch.div(offset, int(window), rounding_mode="floor")
    return torch.bincount(index).cpu().numpy()


@dataclass(frozen=True)
class WindowRates:
    """Event counts per window of one length, over one or several recordings.

    Attributes:
        window: the window's length, in timestamp units.
        time_unit: seconds per timestamp unit (for the rates in events per second).
        events: events in all the recordings.
        mean: events per window on average (all events over the recordings' summed spans).
        p99: the 99th percentile of the counts of consecutive windows (each recording cut
            into windows from its first event; empty windows count, the last one may be
            partial).
        peak: the most events in any window ``[s, s + window)`` of any recording.
    """

    window: float
    time_unit: float
    events: int
    mean: float
    p99: float
    peak: int

    def per_second(self, count: float) -> float:
        """A count per window as events per second."""
        return count / (self.window * self.time_unit)

    def describe(self) -> str:
        """One line: the three rates in events per second, and the window.

        Example:
            >>> WindowRates(1000, 1e-6, 900, 250.0, 300.0, 512).describe()
            'mean 250,000 / p99 300,000 / peak 512,000 events/s in windows of 1 ms'
        """
        seconds = self.window * self.time_unit
        length = f"{seconds * 1e3:g} ms" if seconds < 1 else f"{seconds:g} s"
        return (f"mean {self.per_second(self.mean):,.0f} / p99 {self.per_second(self.p99):,.0f}"
                f" / peak {self.per_second(self.peak):,.0f} events/s in windows of {length}")


def window_rates(
    recordings: Sequence[EventsLike], window: float, time_unit: float | str | None = None
) -> WindowRates:
    """Mean, 99th-percentile and peak event counts per ``window`` over ``recordings``.

    Args:
        recordings: streams of any kind a transform accepts (a transform's outputs, say).
        window: the window's length in the streams' time unit (microseconds for Tonic), > 0.
        time_unit: seconds per timestamp unit, for :meth:`WindowRates.per_second` (default
            1e-6: microseconds; a unit's name such as ``"ms"`` too).

    Returns:
        The :class:`WindowRates`; zeros when the recordings hold no event.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, t, 1] for t in (0, 100, 200, 300, 1500, 2500)])
        >>> rates = window_rates([ev], window=1000)
        >>> rates.peak, rates.mean, rates.per_second(rates.peak)
        (4, 2.4, 4000.0)
    """
    window = check_positive_float("window", window)
    unit = check_time_unit(DEFAULT_TIME_UNIT if time_unit is None else time_unit)
    counts: list[np.ndarray] = []
    events, span, peak = 0, 0.0, 0
    for recording in recordings:
        t = torch.sort(to_events(recording)[0].t).values
        if t.shape[0] == 0:
            continue
        events += t.shape[0]
        span += float(t[-1] - t[0])
        peak = max(peak, peak_count(t, window))
        counts.append(_window_counts(t, window))
    if not counts:
        return WindowRates(window, unit, 0, 0.0, 0.0, 0)
    mean = events * window / span if span > 0 else float(events)
    p99 = float(np.percentile(np.concatenate(counts), 99))
    return WindowRates(window, unit, events, mean, p99, peak)
