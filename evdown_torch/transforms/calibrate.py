"""Event budgets: set a method's one budget setting so that its output hits a target count.

docs/semantics.md, "Event budget": :func:`calibrate` returns a copy of a transform whose budget
setting (the class attribute ``budget_setting``: the contrast ``threshold`` of the
log-luminance methods, the ``weight`` of LIFPooling, the ``keep`` probability of the thinning
control) makes the total output over some recordings as close as the setting allows to a
target, by a deterministic search.

The search works on the logarithm of the setting. It first finds in which direction the
output grows (probing the setting times and divided by 4), then widens a bracket by factors
of 4 until the target lies inside (a step past the end of the setting's allowed range goes
to that end, exactly: a count reachable only there is reached), then narrows it by regula
falsi on ``log(count)`` (the Illinois variant, with bisection where a count is 0), and stops
when the count is within ``rtol`` of the target. Every evaluation runs the transform once on
every recording; counts are remembered, so no setting is run twice. The result is the
evaluated setting whose count is closest to the target.

A peak target (:meth:`BudgetTarget.peak`: at most ``R`` events in any window of ``W``, a
chip's input limit) runs the same search on the output's peak
(:func:`~evdown_torch.transforms.window_rates.peak_count`, the busiest window of any
recording) instead of its total, and returns the evaluated setting with the largest peak not
above ``R`` (within ``rtol`` below it stops the search). Its :class:`Calibration` reports the
output's mean, 99th-percentile and peak window rates (:class:`WindowRates`), which the other
targets report too when given a ``window``.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Generic, Literal, TypeVar, cast

from evdown_torch.checks import (
    DEFAULT_TIME_UNIT,
    OutputLimitError,
    check_choice,
    check_positive_float,
    check_positive_int,
    check_time_unit,
)
from evdown_torch.collate import to_batch
from evdown_torch.events import Events, EventsLike
from evdown_torch.time_units import TIME_UNITS
from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.window_rates import WindowRates, window_rates

__all__ = ["BudgetTarget", "Calibration", "calibrate", "calibration"]

#: The transform's class: the calibrated copy has it too.
D = TypeVar("D", bound=Downscaler)


@dataclass(frozen=True)
class BudgetTarget:
    """What the output over the calibration recordings should be.

    Attributes:
        kind: ``"ratio"`` (output events per input event), ``"count"`` (output events, all
            recordings together), ``"rate"`` (output events per second of recording, on
            average) or ``"peak"`` (at most ``value`` output events in any window of
            ``window``: a chip's input limit; docs/semantics.md, "Peak budget").
        value: the target, positive.
        time_unit: seconds per timestamp unit, for ``"rate"`` and ``"peak"`` only (``None``,
            the default, is 1e-6: microseconds; see
            :func:`~evdown_torch.checks.check_time_unit`). The other kinds have no time in
            them and refuse one. Stored as given (``None`` stays ``None``, so a copy of
            another kind stays valid).
        window: the window's length in timestamp units, for ``"peak"`` only.

    Example:
        >>> BudgetTarget.ratio(0.1).events(input_events=5000, duration=2e6)
        500.0
        >>> BudgetTarget.rate(300.0).events(input_events=5000, duration=2e6)
        600.0
        >>> BudgetTarget.peak(500, window=1000).events(input_events=5000, duration=2e6)
        500.0
    """

    kind: Literal["ratio", "count", "rate", "peak"]
    value: float
    time_unit: float | None = None
    window: float | None = None

    def __post_init__(self) -> None:
        check_choice("target kind", self.kind, ("ratio", "count", "rate", "peak"))
        object.__setattr__(self, "value", check_positive_float("target", self.value))
        if self.kind == "peak":
            if self.window is None:
                raise ValueError("a peak target needs a window (timestamp units)")
            object.__setattr__(self, "window", check_positive_float("window", self.window))
        elif self.window is not None:
            raise ValueError(
                f"window={self.window!r} applies only to a peak target (events per window); "
                f"a {self.kind} target has none"
            )
        if self.kind not in ("rate", "peak"):
            if self.time_unit is not None:
                raise ValueError(
                    f"time_unit={self.time_unit!r} applies only to a rate or peak target "
                    f"(events per second); a {self.kind} target has no time in it"
                )
            return
        if self.time_unit is not None:
            object.__setattr__(self, "time_unit", check_time_unit(self.time_unit))

    @classmethod
    def ratio(cls, value: float) -> BudgetTarget:
        """``value`` output events per input event."""
        return cls("ratio", value)

    @classmethod
    def count(cls, value: float) -> BudgetTarget:
        """``value`` output events over all the recordings together."""
        return cls("count", value)

    @classmethod
    def rate(cls, events_per_second: float, time_unit: float | None = None) -> BudgetTarget:
        """``events_per_second`` output events per second (timestamps count ``time_unit`` s)."""
        return cls("rate", events_per_second, time_unit)

    @classmethod
    def peak(cls, max_events: float, window: float,
             time_unit: float | None = None) -> BudgetTarget:
        """At most ``max_events`` output events in any window of ``window`` timestamp units.

        ``BudgetTarget.peak(500, window=1000)``: 500 events per millisecond at the busiest
        (500 k events/s at peak) for microsecond timestamps. ``time_unit`` (seconds per
        timestamp unit, default 1e-6) only turns the reported rates into events per second.
        """
        return cls("peak", max_events, time_unit, window)

    @classmethod
    def parse(cls, text: str) -> BudgetTarget:
        """A target written ``ratio=R``, ``count=N``, ``rate=HZ`` or ``peak=HZ/WINDOW``.

        For microsecond timestamps (the command line's). ``peak=500000/1ms`` is a peak rate
        of 500,000 events per second in windows of 1 ms, i.e. ``BudgetTarget.peak(500,
        1000)``; the window takes a unit (``s``, ``ms``, ``us``, ``ns``) and the rate times
        the window must be a whole number of events.

        Raises:
            ValueError: naming the forms accepted, for anything else.

        Example:
            >>> BudgetTarget.parse("peak=500000/1ms")
            BudgetTarget(kind='peak', value=500.0, time_unit=None, window=1000.0)
            >>> BudgetTarget.parse("ratio=0.05").value
            0.05
        """
        forms = "ratio=R, count=N, rate=EVENTS_PER_S or peak=EVENTS_PER_S/WINDOW (e.g. 1ms)"
        kind, sep, value = (part.strip() for part in str(text).partition("="))
        if not sep or kind not in ("ratio", "count", "rate", "peak"):
            raise ValueError(f"a budget must be {forms}, got {text!r}")
        rate, _, window = value.partition("/")
        if (kind == "peak") != bool(window):
            raise ValueError(f"a budget must be {forms}, got {text!r}")
        try:
            number = float(rate)
        except ValueError:
            raise ValueError(f"a budget must be {forms}, got {text!r}") from None
        if kind != "peak":
            return cls(cast(Literal["ratio", "count", "rate"], kind), number)
        found = re.fullmatch(r"([0-9.eE+-]+)\s*(s|ms|us|ns)", window.strip())
        try:
            if found is None:
                raise ValueError
            length_us = float(found[1]) * TIME_UNITS[found[2]]
        except ValueError:
            raise ValueError(f"the window of {text!r} must be a number and a unit (s, ms, us "
                             "or ns), e.g. 1ms") from None
        check_positive_float("peak window", length_us)
        per_window = check_positive_float("peak rate", number) * length_us * 1e-6
        if abs(per_window - round(per_window)) > 1e-9 * per_window or round(per_window) < 1:
            raise ValueError(
                f"{text!r} allows {per_window:g} events per window: choose a rate and a window "
                "whose product is a whole number of events (at least 1)"
            )
        return cls.peak(float(round(per_window)), length_us)

    def events(self, *, input_events: int, duration: float) -> float:
        """The target as a count: a total (a peak target: the most events in one window).

        Args:
            input_events: the recordings' input events, all together.
            duration: the recordings' summed duration, in timestamp units.
        """
        if self.kind == "ratio":
            return self.value * input_events
        if self.kind in ("count", "peak"):
            return self.value
        if duration <= 0:
            raise ValueError("a rate target needs recordings that span a positive duration")
        time_unit = DEFAULT_TIME_UNIT if self.time_unit is None else self.time_unit
        return self.value * duration * time_unit


@dataclass(frozen=True)
class Calibration(Generic[D]):
    """What :func:`calibration` found.

    Attributes:
        transform: the calibrated copy of the transform.
        value: its budget setting.
        count: its total output over the recordings (for a peak target: its peak, the most
            events in one window).
        target: the target as a count (:meth:`BudgetTarget.events`).
        evaluations: how many settings were run.
        rates: its output's mean, 99th-percentile and peak window rates, for a peak target
            or a ``window`` given (else ``None``).
    """

    transform: D
    value: float
    count: int
    target: float
    evaluations: int
    rates: WindowRates | None = None


def calibrate(
    transform: D,
    recordings: Sequence[EventsLike],
    target: BudgetTarget,
    *,
    rtol: float = 0.01,
    max_evaluations: int = 40,
) -> D:
    """A copy of ``transform`` whose budget setting makes the output hit ``target``.

    Args:
        transform: a downscaler whose class names a ``budget_setting`` (EventCount,
            LinearEstimation, CubicEstimation, LIFPooling, ThinnedDownsample, ...); its
            current setting is where the search starts, its other settings are kept.
        recordings: the calibration streams, any kind the transform accepts (at least one
            event in all).
        target: the wanted output (:class:`BudgetTarget`): a total, or a peak per window.
        rtol: stop once the count is within this fraction of the target (below it, for a
            peak).
        max_evaluations: run the transform with at most this many settings.

    Returns:
        The calibrated transform (the input transform is not modified).

    Raises:
        ValueError: for a transform without a budget setting, no events, recordings with
            both integer and float timestamps (or on several devices; refused before any
            run), or an output that does not depend on the setting. A setting whose output
            exceeds the output limit counts as more than any target; any other error of the
            transform is raised as it is.

    Example:
        >>> import torch
        >>> from evdown_torch.transforms import EventCount
        >>> g = torch.Generator().manual_seed(0)
        >>> ev = torch.stack([torch.randint(0, 32, (20_000,), generator=g),
        ...                   torch.randint(0, 32, (20_000,), generator=g),
        ...                   torch.arange(20_000), torch.randint(0, 2, (20_000,), generator=g)], 1)
        >>> down = calibrate(EventCount((32, 32, 2), 4), [ev], BudgetTarget.ratio(0.05))
        >>> abs(len(down(ev)) / 20_000 - 0.05) < 0.05 * 0.05
        True

        At most 40 events in any window of 1,000 timestamp units (40 k events/s at peak):

        >>> found = calibration(EventCount((32, 32, 2), 4), [ev], BudgetTarget.peak(40, 1000))
        >>> found.count <= 40, found.rates.peak == found.count
        (True, True)
    """
    return calibration(transform, recordings, target, rtol=rtol,
                       max_evaluations=max_evaluations).transform


def calibration(
    transform: D,
    recordings: Sequence[EventsLike],
    target: BudgetTarget,
    *,
    rtol: float = 0.01,
    max_evaluations: int = 40,
    window: float | None = None,
) -> Calibration[D]:
    """As :func:`calibrate`, returning what the search found (:class:`Calibration`).

    ``window`` (timestamp units): also report the output's window rates
    (:attr:`Calibration.rates`) for a ratio, count or rate target; a peak target reports them
    in its own window.
    """
    if not isinstance(transform, Downscaler):
        raise TypeError(f"transform must be a Downscaler, got {type(transform).__name__}")
    setting = type(transform).budget_setting
    if setting is None:
        raise ValueError(
            f"{type(transform).__name__} has no budget setting: its output count is fixed by "
            "its input"
        )
    if not isinstance(target, BudgetTarget):
        example = target if isinstance(target, (int, float)) and not isinstance(
            target, bool) else 0.1
        raise TypeError(
            f"target must be a BudgetTarget, got {target!r}: give BudgetTarget.ratio(r) for a "
            f"fraction of the input events (e.g. BudgetTarget.ratio({example!r})), "
            "BudgetTarget.count(n) for events over all recordings, BudgetTarget.rate(hz) for "
            "events per second or BudgetTarget.peak(n, window) for at most n events per window")
    rtol = check_positive_float("rtol", rtol)
    max_evaluations = check_positive_int("max_evaluations", max_evaluations)
    if target.kind == "peak":
        window = target.window
    elif window is not None:
        window = check_positive_float("window", window)
    try:  # one device, one clock: integer and float timestamps do not mix
        streams = list(to_batch(recordings, transform.sensor_size)[0].unbind())
    except ValueError as error:
        raise ValueError(f"calibration recordings: {error}") from None
    inputs = sum(s.num_events for s in streams)
    if inputs == 0:
        raise ValueError("calibrate needs recordings with at least one event")
    duration = sum(float(s.t.max() - s.t.min()) for s in streams if s.num_events)
    wanted = target.events(input_events=inputs, duration=duration)
    search = _Search(transform, setting, streams, wanted, max_evaluations,
                     _Measure(target.kind == "peak", window, target.time_unit))
    best = search.run(float(getattr(transform, setting)), rtol)
    return Calibration(search.build(best), best, int(search.counts[best]), wanted,
                       len(search.counts), search.rates.get(best))


@dataclass(frozen=True)
class _Measure:
    """What a search counts: the total (or, ``peak``, the busiest window) of the outputs."""

    peak: bool = False
    window: float | None = None  # also measure the window rates (a peak's own window)
    time_unit: float | None = None


class _Search(Generic[D]):
    """The output count as a function of the setting, remembered, and the search over it."""

    def __init__(self, transform: D, setting: str, streams: list[Events],
                 wanted: float, max_evaluations: int, measure: _Measure) -> None:
        self.transform, self.setting, self.streams = transform, setting, streams
        self.wanted, self.max_evaluations = wanted, max_evaluations
        self.measure = measure
        self.counts: dict[float, float] = {}
        self.rates: dict[float, WindowRates] = {}

    def build(self, value: float) -> D:
        # The setting is named at run time: no field's type can be checked here (the
        # transform's __post_init__ checks the value).
        changes: dict[str, Any] = {self.setting: value}
        return replace(self.transform, **changes)

    def valid(self, value: float) -> bool:
        try:
            self.build(value)
        except (ValueError, TypeError):
            return False
        return math.isfinite(value) and value > 0

    def count(self, value: float) -> float:
        if value not in self.counts:
            down = self.build(value)
            try:
                # one pass over every recording (Events in, Events out)
                outputs = cast(list[Events], down.batch(self.streams))
            except OutputLimitError:  # an output too large to produce: more than any target
                self.counts[value] = math.inf
                return math.inf
            self.counts[value] = float(sum(out.num_events for out in outputs))
            if self.measure.window is not None:
                rates = window_rates(outputs, self.measure.window, self.measure.time_unit)
                self.rates[value] = rates
                if self.measure.peak:
                    self.counts[value] = float(rates.peak)
        return self.counts[value]

    def edge(self, inside: float, outside: float) -> float:
        """The valid setting nearest ``outside``, from ``inside`` (valid) toward ``outside``.

        ``outside`` is not valid. A bisection over the floats between them, exact to the last
        one (positive floats sort as their bit patterns do), and cheap, as it only builds
        transforms.
        """
        def bits(value: float) -> int:
            return struct.unpack("<q", struct.pack("<d", value))[0]

        def value(pattern: int) -> float:
            return struct.unpack("<d", struct.pack("<q", pattern))[0]

        good, bad = bits(inside), bits(max(outside, 0.0))
        while abs(bad - good) > 1:
            middle = (good + bad) // 2
            if self.valid(value(middle)):
                good = middle
            else:
                bad = middle
        return value(good)

    def spent(self) -> bool:
        return len(self.counts) >= self.max_evaluations

    def close(self, value: float, rtol: float) -> bool:
        if self.measure.peak:  # at most the target, and within rtol below it
            return (1 - rtol) * self.wanted <= self.count(value) <= self.wanted
        return abs(self.count(value) - self.wanted) <= rtol * self.wanted

    def best(self) -> float:
        if self.measure.peak:
            under = [v for v in self.counts if self.counts[v] <= self.wanted]
            if under:  # the largest peak not above the target
                return min(under, key=lambda v: (-self.counts[v], v))
            return min(self.counts, key=lambda v: (self.counts[v], v))
        return min(self.counts, key=lambda v: (abs(self.counts[v] - self.wanted), v))

    def direction(self, start: float) -> int:
        """+1 when the count grows with the setting, -1 when it falls."""
        base = self.count(start)
        for k in (1, 2, 3):
            for sign in (1, -1):
                probe = start * 4.0 ** (sign * k)
                if not self.valid(probe) or self.spent():
                    continue
                if self.count(probe) != base:
                    return sign if self.count(probe) > base else -sign
        raise ValueError(
            f"the output of {type(self.transform).__name__} does not change with "
            f"{self.setting} around {start:g} (always {base:.0f} events); it cannot be calibrated"
        )

    def run(self, start: float, rtol: float) -> float:
        if not self.valid(start):
            raise ValueError(f"{self.setting} = {start!r} is not a valid starting point")
        if self.close(start, rtol):
            return start
        grows = self.direction(start)
        # Widen: step the setting (by 4x) the way that moves the count toward the target.
        value = self.best()
        below = self.count(value) < self.wanted
        step = 4.0 ** (grows if below else -grows)
        other = value
        while (self.count(other) < self.wanted) == below:
            if self.close(other, rtol) or self.spent():
                return self.best()
            following = other * step
            if not self.valid(following):  # past the setting's range: try its end first
                following = self.edge(other, following)
                if following == other:
                    return self.best()
            value, other = other, following
        # Narrow: regula falsi (Illinois) on log(count) against log(setting).
        lo, hi = sorted((value, other))
        # A peak (one window's count) jumps as the setting moves: settings 1e-4 apart are
        # as close as it is worth telling apart.
        narrowest = 1e-4 if self.measure.peak else 1e-9
        log_target = math.log(self.wanted)
        keep_lo = keep_hi = 1.0
        side = 0
        while not self.spent():
            c_lo, c_hi = self.count(lo), self.count(hi)
            if self.close(lo, rtol) or self.close(hi, rtol) or hi / lo - 1.0 < narrowest:
                break
            u_lo, u_hi = math.log(lo), math.log(hi)
            if 0 < c_lo < math.inf and 0 < c_hi < math.inf and c_lo != c_hi:
                g_lo = (math.log(c_lo) - log_target) * keep_lo
                g_hi = (math.log(c_hi) - log_target) * keep_hi
                u = u_lo - g_lo * (u_hi - u_lo) / (g_hi - g_lo)
                u = min(max(u, u_lo + 1e-3 * (u_hi - u_lo)), u_hi - 1e-3 * (u_hi - u_lo))
            else:
                u = 0.5 * (u_lo + u_hi)
            middle = math.exp(u)
            if (self.count(middle) < self.wanted) == (c_lo < self.wanted):
                lo = middle
                keep_hi = keep_hi * 0.5 if side == -1 else 1.0
                keep_lo, side = 1.0, -1
            else:
                hi = middle
                keep_lo = keep_lo * 0.5 if side == 1 else 1.0
                keep_hi, side = 1.0, 1
        return self.best()
