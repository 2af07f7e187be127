"""Rate limiter kernel: a token bucket of ``max_events`` per ``window`` that drops the overflow.

The bucket (docs/semantics.md, "Rate limiter") holds up to ``R = max_events`` tokens, starts
full, refills continuously at ``R`` tokens per ``W = window`` and never holds more than ``R``;
an event passes when the bucket holds a whole token at its time and takes it, else it is
dropped. The content is counted in units of ``1 / W`` token (divided by ``g = gcd(R, W)``):
an event costs ``w = W / g``, the bucket refills ``r = R / g`` per time unit and holds at most
``c = R * W / g``, so integer timestamps give integer arithmetic, exact.

A token bucket is sequential, but between two kinds of moments it has a closed form that is
a running maximum or minimum, which torch computes in one pass (``cummax``, ``cummin``):

* **No drop since the bucket was last full** ("full" episode, from an origin ``(t_o, L_o)``):
  events ``i = 1, 2, ...`` all pass, and the content before event ``i`` is
  ``V_i + min(L_o, c - max_{j <= i} V_j)`` with ``V_i = r (t_i - t_o) - (i - 1) w`` (the
  content is capped at ``c`` wherever the uncapped one would exceed it). The episode ends at
  the first event that finds less than ``w``: it is dropped.
* **Overflow** (from a dropped event or a resumed stream, origin ``(t_o, L_o)``): while the
  cap is not reached, event ``i`` passes iff ``P_{i-1} < q_i`` where
  ``q_i = floor((L_o + r (t_i - t_o)) / w)`` counts the tokens made so far and ``P`` the
  passes, so ``P_i = min(P_{i-1} + 1, q_i)``, whose solution is
  ``P_i = i + min(0, min_{j <= i} (q_j - j))``. The episode ends at the first event before
  which the uncapped content would exceed ``c``: the bucket is full there, and a full episode
  starts with it.

So the kernel loops over episodes, not events: each one costs a few vectorised passes over
its events (a chunk goes in one block until an episode ends in it; then blocks of twice the
last episode's length, doubling while none ends, find the next end without rereading the
rest of the chunk).
An overflow episode lasts at least ``W (1 - 1 / R)`` (the bucket must refill), so a stream
has at most about ``duration / W`` of them, and as many only where it overflows in every
window. Integer timestamps: the gaps between events are capped at ``W`` (a longer gap fills
the bucket anyway) and each block starts afresh from the last event's exact content, so the
arithmetic stays exact and inside int64. Float timestamps: every value is computed from its
episode's origin and index, which the state carries, so the same events give the same
float64 values in any chunking and a session equals the batch call bit for bit.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import where_true
from evdown_torch.checks import check_positive_float, check_positive_int, check_sensor_size
from evdown_torch.events import Events
from evdown_torch.transforms.functional.protocol import Method, run_protocol

__all__ = [
    "RATE_LIMIT",
    "Bucket",
    "RateLimitSettings",
    "RateLimitState",
    "bucket",
    "limit_rate",
    "rate_limit_init",
    "rate_limit_step",
]

#: The bucket's capacity in its integer units (``R * W / gcd(R, W)``) stays below this, so that
#: blocks of at least 1,024 events keep every sum inside int64.
MAX_INTEGER_CAPACITY = 2**52
_MIN_BLOCK = 256
_MAX_BLOCK = 1 << 20
_INT64_LIMIT = 2**62


@dataclass(frozen=True)
class RateLimitSettings:
    """The rate limiter's settings, checked once.

    Attributes:
        max_events: ``R``, the bucket's capacity and its refill per window, a positive integer.
        window: ``W``, in the stream's time unit (microseconds for Tonic), > 0; a whole
            number for integer timestamps (checked at call time).
        sensor_size: ``(W, H, P)`` to check coordinates against, or ``None``.
    """

    max_events: int
    window: int | float
    sensor_size: tuple[int, int, int] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_events", check_positive_int("max_events",
                                                                  self.max_events))
        check_positive_float("window", self.window)
        if self.sensor_size is not None:
            object.__setattr__(self, "sensor_size", check_sensor_size(self.sensor_size))


class Bucket(NamedTuple):
    """The bucket in the units of the stream's arithmetic.

    Attributes:
        cost: what one event takes (``w``).
        refill: what one time unit adds (``r``).
        capacity: the most it holds (``c = R * w = r * W``).
        window: ``W``, beyond which a gap fills the bucket whatever it held.
    """

    cost: int | float
    refill: int | float
    capacity: int | float
    window: int | float


def bucket(settings: RateLimitSettings, integer: bool) -> Bucket:
    """The bucket of ``settings`` for integer (exact) or float timestamps.

    Raises:
        ValueError: for integer timestamps, a ``window`` that is not a whole number, or a
            capacity of :data:`MAX_INTEGER_CAPACITY` or more in integer units.

    Example:
        >>> bucket(RateLimitSettings(500, 1000), integer=True)
        Bucket(cost=2, refill=1, capacity=1000, window=1000)
    """
    events, window = settings.max_events, settings.window
    if not integer:
        return Bucket(float(window), float(events), float(events) * float(window),
                      float(window))
    if not (isinstance(window, numbers.Integral) or float(window).is_integer()):
        raise ValueError(
            f"window must be a whole number for integer timestamps (the bucket is counted "
            f"exactly in 1/window tokens), got {window!r}"
        )
    whole = int(window)
    g = math.gcd(events, whole)
    capacity = events * whole // g
    if capacity >= MAX_INTEGER_CAPACITY:
        raise ValueError(
            f"max_events={events} per window={whole} is too fine a rate to count exactly: "
            f"max_events * window / gcd(max_events, window) = {capacity:,} must stay below "
            f"2**52; round max_events or window to share more factors"
        )
    return Bucket(whole // g, events // g, capacity, whole)


class RateLimitState(NamedTuple):
    """State of a rate-limited stream between chunks.

    Attributes:
        full: ``True`` while no event was dropped since the bucket was last full (a "full"
            episode), ``False`` during an overflow episode.
        origin_t: the time the episode's values count from.
        origin_level: the bucket's content there (in :class:`Bucket` units).
        since: events of the episode after the origin (float timestamps; 0 for integer ones,
            whose origin moves to the last event after each block).
        extreme: a full episode's running maximum of ``V`` (``None`` before its first event),
            an overflow episode's running minimum of ``min(0, q_j - j)``.
        dropped: events dropped so far in the stream.
    """

    full: bool
    origin_t: int | float
    origin_level: int | float
    since: int
    extreme: int | float | None
    dropped: int


def rate_limit_init(settings: RateLimitSettings, events: Events) -> RateLimitState:
    """``init_state``: a full bucket at the stream's first timestamp."""
    integer = not events.t.is_floating_point()
    capacity = bucket(settings, integer).capacity
    return RateLimitState(True, events.t[0].item(), capacity, 0, None, 0)


def _first(mask: Tensor) -> int | None:
    """The position of the first True of ``mask``, ``None`` when there is none."""
    at = where_true(mask)
    return int(at[0]) if at.shape[0] else None


def _elapsed(t: Tensor, state: RateLimitState, bucket: Bucket) -> Tensor:
    """Time since the episode's origin: exact, gaps capped at ``W``, for integer ``t``."""
    if t.is_floating_point():
        return t - state.origin_t
    gaps = torch.cat([t[:1] - state.origin_t, torch.diff(t)])
    return gaps.clamp_(max=int(bucket.window)).cumsum_(0)


def _index(t: Tensor, since: int) -> Tensor:
    """``since + 1, since + 2, ...``: each event's index in its episode, in ``t``'s dtype."""
    return torch.arange(since + 1, since + 1 + t.shape[0], dtype=t.dtype, device=t.device)


def _full_block(t: Tensor, state: RateLimitState, b: Bucket
                ) -> tuple[int | None, RateLimitState]:
    """Events ``t`` in a full episode: the first one dropped (``None``: none) and the state."""
    index = _index(t, state.since)
    v = _elapsed(t, state, b).mul_(b.refill).sub_((index - 1).mul_(b.cost))
    top = torch.cummax(v, 0).values
    if state.extreme is not None:
        top.clamp_(min=state.extreme)
    before = v + (b.capacity - top).clamp_(max=state.origin_level)  # content before each
    k = _first(before < b.cost)
    if k is not None:  # event k finds less than a token: dropped, an overflow starts
        return k, RateLimitState(False, t[k].item(), before[k].item(), 0, 0,
                                 state.dropped + 1)
    if t.is_floating_point():
        return None, state._replace(since=state.since + t.shape[0], extreme=top[-1].item())
    return None, state._replace(origin_t=t[-1].item(),
                                origin_level=before[-1].item() - b.cost, extreme=None)


def _overflow_block(t: Tensor, state: RateLimitState, b: Bucket
                    ) -> tuple[int | None, Tensor, RateLimitState]:
    """Events ``t`` in an overflow episode.

    Returns:
        ``(k, passed, state)``: the first event before which the bucket is full (``None``:
        none; it starts a full episode and is not decided here), whether each event before
        it passes, and the state after them.
    """
    index = _index(t, state.since)
    start = 0 if state.extreme is None else state.extreme  # min(0, q_j - j) so far
    made = _elapsed(t, state, b).mul_(b.refill).add_(state.origin_level)  # tokens made
    if t.is_floating_point():
        tokens = torch.floor(made / b.cost)
    else:
        tokens = torch.div(made, b.cost, rounding_mode="floor")
    low = torch.cummin(tokens.sub_(index), 0).values.clamp_(max=start)
    passes = index.add_(low)  # P_i, the passes of the episode after event i
    passes_before = torch.cat([passes.new_tensor([state.since + start]),
                               passes[:-1]])
    k = _first(made - passes_before * b.cost > b.capacity)
    end = t.shape[0] if k is None else k
    passed = passes[:end] > passes_before[:end]
    dropped = state.dropped + end - int(passed.sum())
    if k is not None:  # full before event k: a full episode starts with it
        return k, passed, RateLimitState(True, t[k].item(), b.capacity, 0, None, dropped)
    if t.is_floating_point():
        return None, passed, state._replace(since=state.since + end, extreme=low[-1].item(),
                                            dropped=dropped)
    level = made[-1].item() - passes[-1].item() * b.cost
    return None, passed, RateLimitState(False, t[-1].item(), level, 0, 0, dropped)


def rate_limit_step(
    events: Events, state: RateLimitState, settings: RateLimitSettings
) -> tuple[Events, RateLimitState]:
    """``step``: one time-sorted chunk; returns the events that pass and the new state.

    Raises:
        ValueError: for integer timestamps spanning ``2**62`` or more from the episode's
            origin, or a window :func:`bucket` refuses.
    """
    t = events.t
    n = t.shape[0]
    integer = not t.is_floating_point()
    b = bucket(settings, integer)
    if integer and int(t[-1]) - int(state.origin_t) >= _INT64_LIMIT:
        raise ValueError(
            f"the timestamps span 2**62 or more time units (from {state.origin_t} to "
            f"{int(t[-1])}): their differences do not fit in int64"
        )
    largest = _MAX_BLOCK
    if integer:  # every sum of a block stays below 2**62
        largest = max(1, min(_MAX_BLOCK, _INT64_LIMIT // (int(b.capacity) + int(b.cost))))
    keep = torch.ones(n, dtype=torch.bool, device=t.device)
    pos, size = 0, largest  # the whole chunk at once, unless an episode ends in it
    while pos < n:
        block = t[pos:min(n, pos + size)]
        if state.full:
            k, state = _full_block(block, state, b)
            if k is not None:
                keep[pos + k] = False
            step = block.shape[0] if k is None else k + 1
        else:
            k, passed, state = _overflow_block(block, state, b)
            keep[pos:pos + passed.shape[0]] = passed
            step = passed.shape[0]
        pos += step
        # Next block: twice this one when no episode ended in it, else twice the episode's
        # part in it. Each block then costs at most twice the episode before it, so the
        # blocks of a chunk cost O(its events) plus a few passes' overhead per episode.
        size = min(2 * (size if k is None else max(step, _MIN_BLOCK // 2)), largest)
    return events.select(keep), state


def limit_rate(events: Events, *, max_events: int, window: int | float) -> Events:
    """The token bucket over a whole stream (docs/semantics.md, "Rate limiter").

    Args:
        events: ``N`` events (any order; taken in stable time order).
        max_events: ``R``: the bucket's capacity and its refill per ``window``.
        window: ``W`` in the stream's time unit (microseconds for Tonic), > 0; a whole
            number for int64 timestamps.

    Returns:
        The events that pass, sorted by ``t``; ``N`` minus their number were dropped.

    Example:
        >>> ev = Events.from_columns([0] * 7, [0] * 7, [0, 0, 0, 1, 2, 5, 6], [1] * 7)
        >>> limit_rate(ev, max_events=2, window=4).t.tolist()  # a token back every 2
        [0, 0, 2, 5, 6]
    """
    return run_protocol(RATE_LIMIT, RateLimitSettings(max_events, window), events)


#: RateLimiter's kernels (:class:`~evdown_torch.RateLimiter`): causal, its state the bucket.
RATE_LIMIT: Method[RateLimitSettings, RateLimitState] = Method(rate_limit_init, rate_limit_step)
