"""DensitySubsampling kernel (docs/semantics.md, method 9): keep events where they are dense.

Each event's local density is the Gaussian-weighted sum, over the ``k x k`` patch around its
pixel, of every patch pixel's decayed count of same-polarity events up to the event (each
count decays as ``exp(-dt / tau)`` and gains 1 per event). The event is kept when its draw
``u_e`` (:func:`~evdown_torch.transforms.functional.draws.event_uniforms`) is below ``s`` times its
density; kept events are then downsampled. Causal: each event is decided at once.

How it is computed, without a loop over events:

* **A pixel's decayed count** after each of its events, ``S_k = 1 + exp(-(t_k - t_{k-1}) /
  tau) * S_{k-1}``, is a linear recurrence. The events are grouped by pixel and polarity and
  the recurrence runs as a doubling scan (Hillis-Steele): pass ``d`` (1, 2, 4, ...) adds to
  each ``S_k`` the value ``d`` places earlier in its group times ``exp(-(t_k - t_{k-d}) /
  tau)``, so ``ceil(log2 m)`` passes serve groups of up to ``m`` events. Every factor is the
  exponential of a time difference that is not positive: nothing can overflow, whatever the
  stream's length or clock, and no time origin is needed (a cumulative sum of
  ``exp(t_i / tau)`` would overflow after ``709 tau``). Each value is a sum of positive terms,
  each a product of at most ``ceil(log2 m)`` rounded exponentials: a few ``1e-15`` relative
  (the bound is in docs/semantics.md, "How the subsamplers are computed").
* **The patch sum** needs, for each event and each pixel of its patch, that pixel's count at
  the event: the pixel's last event up to this one in stream order is found by one binary
  search (``searchsorted`` over the events sorted by pixel, then stream position; keys on the
  sensor padded by the patch radius, so no lookup needs a bounds test; on the CPU one compiled
  sweep in stream order finds the same event, :mod:`..compiled.density`), and its ``S`` decays
  to the event's time. The ``k * k`` neighbours go through in groups whose temporaries stay
  near a million elements, added in a fixed order.
* **A stream** carries, per pixel and polarity, the decayed count after its last event and
  that event's time (:class:`DensityState`: bounded by the sensor), plus the number of events
  seen and the first timestamp (the draws' position and clock origin).

A session and the whole-stream call can round a density differently (the scan runs over other
groupings), within that bound: their decisions can differ only for an event whose draw lies
that close to ``s * density``, about one chance in ``10**14`` per event.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import (
    changes,
    chunk_bounds,
    last_of_runs,
    run_index,
    searchsorted_ascending,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.checks import (
    check_non_negative_int,
    check_positive_float,
    check_positive_int,
    check_time_constant,
)
from evdown_torch.events import Events, sort_by_time
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.downsample import to_regions
from evdown_torch.transforms.functional.draws import chunk_uniforms
from evdown_torch.transforms.functional.protocol import Method, step_in_pieces
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = [
    "DENSITY",
    "DensitySettings",
    "DensityState",
    "axis_weights",
    "density_init",
    "density_step",
    "density_subsampling",
    "density_whole",
    "event_density",
    "patch_offsets",
]

#: Elements of the temporaries of one group of neighbour lookups (events x neighbours).
LOOKUP_ELEMENTS = 1 << 20

_INT64_LIMIT = 1 << 62


@dataclass(frozen=True)
class DensitySettings(RegionSettings):
    """DensitySubsampling's settings, checked once.

    Attributes:
        tau: decay time constant of the per-pixel counts, in the stream's time unit
            (microseconds for Tonic), > 0 (``math.inf``: no decay).
        k: side of the square patch, an odd positive integer.
        s: the budget setting, > 0: an event is kept with probability ``min(1, s * density)``.
        seed: non-negative integer mixed into every event's draw.
    """

    tau: float = 30_000.0
    k: int = 7
    s: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "tau", check_time_constant("tau", self.tau))
        k = check_positive_int("k", self.k)
        if k % 2 == 0:
            raise ValueError(f"k must be an odd positive integer (a patch centred on the "
                             f"pixel), got {k}")
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "s", check_positive_float("s", self.s))
        object.__setattr__(self, "seed", check_non_negative_int("seed", self.seed))


def _weight(squared: int, k: int) -> float:
    """The patch's weight at ``squared`` distance: ``exp(-squared / (2 sigma^2))``, sigma k / 5."""
    sigma = k / 5
    return math.exp(-squared / (2 * sigma * sigma))


def patch_offsets(k: int) -> list[tuple[int, int, float]]:
    """The ``k x k`` patch: ``(dx, dy, w)`` in row-major order, ``w = exp(-r^2 / (2 sigma^2))``.

    ``sigma = k / 5``; the centre has ``w = 1``.

    Example:
        >>> [(dx, dy, round(w, 4)) for dx, dy, w in patch_offsets(3)][:2]
        [(-1, -1, 0.0622), (0, -1, 0.2494)]
    """
    r = k // 2
    return [(dx, dy, _weight(dx * dx + dy * dy, k))
            for dy in range(-r, r + 1) for dx in range(-r, r + 1)]


@functools.cache
def axis_weights(k: int) -> Tensor:
    """The patch's weights along one axis, ``g(d) = exp(-d^2 / (2 sigma^2))`` at ``d = -r..r``.

    ``w = g(dx) * g(dy)`` (exactly, for the exact exponentials): the compiled loop sums a
    patch as rows (:mod:`.compiled.density`). ``(k,)`` float64, shared, never written.

    Example:
        >>> [round(w, 4) for w in axis_weights(3).tolist()]
        [0.2494, 1.0, 0.2494]
    """
    r = k // 2
    return torch.tensor([_weight(d * d, k) for d in range(-r, r + 1)], dtype=torch.float64)


class DensityState(NamedTuple):
    """A DensitySubsampling stream between chunks (bounded by the sensor).

    Attributes:
        decayed: ``(2 * H' * W',)`` float64 decayed count of each pixel and polarity just
            after its last event (0: no event yet), on the sensor padded by ``r = k // 2``
            on every side (``W' = W + 2r``, ``H' = H + 2r``); index
            ``(p * H' + y + r) * W' + x + r``.
        last_t: ``(2 * H' * W',)`` time of that last event (the stream's ``t`` dtype).
        seen: events seen so far (the next event's position in the stream).
        origin: the stream's first timestamp (the draws' clock origin).
    """

    decayed: Tensor
    last_t: Tensor
    seen: int
    origin: int | float


def _decay(elapsed: Tensor, tau: float) -> Tensor:
    """``exp(-elapsed / tau)`` in float64 for time differences ``elapsed >= 0``."""
    return torch.exp(elapsed.to(torch.float64).div_(-tau))


def _padded(settings: DensitySettings) -> tuple[int, int, int]:
    """``(W + 2r, H + 2r, r)``: the sensor padded by the patch radius ``r`` on every side.

    On the padded sensor every patch pixel of an event has a key, so no lookup needs a
    bounds test: the padding never holds an event.
    """
    width, height, _ = settings.sensor_size
    r = settings.k // 2
    return width + 2 * r, height + 2 * r, r


def _pixel_keys(events: Events, settings: DensitySettings) -> Tensor:
    """``(N,)`` int64 key of each event's pixel and polarity on the padded sensor."""
    width, height, r = _padded(settings)
    return (events.p.to(torch.int64) * height + events.y + r) * width + events.x + r


def _decayed_counts(t: Tensor, starts: Tensor, first_at: Tensor, initial: Tensor | None,
                    tau: float) -> Tensor:
    """Each event's pixel count just after it, by a doubling scan (see the module docstring).

    Args:
        t: ``(N,)`` times of events grouped by pixel and polarity, in stream order within a
            group.
        starts: ``(N,)`` bool, True at each group's first event.
        first_at: ``(G,)`` int64 first position of each group, ascending, the first 0.
        initial: ``(G,)`` float64 decayed count each group carries to its first event (from
            earlier chunks), or ``None`` (none).
        tau: the decay time constant.

    Returns:
        ``(N,)`` float64 ``S`` after each event.
    """
    n = t.shape[0]
    counts = torch.ones(n, dtype=torch.float64, device=t.device)
    if initial is not None:
        counts.index_add_(0, first_at, initial)
    lengths = last_of_runs(first_at, n) - first_at + 1
    longest = int(lengths.max())
    if longest == 1:
        return counts
    group_start = take(first_at, run_index(starts))
    rank = torch.arange(n, device=t.device) - group_start
    step = 1
    while step < longest:
        reach = counts[:-step] * _decay(t[step:] - t[:-step], tau)
        reach.masked_fill_(rank[step:] < step, 0.0)
        counts = counts.clone()
        counts[step:] += reach
        step *= 2
    return counts


def _density_sorted(
    events: Events, settings: DensitySettings, state: DensityState | None
) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]]:
    """Densities of time-sorted events continuing ``state`` (``None``: a fresh stream).

    Returns:
        ``(density, (keys, counts, times))``: ``(N,)`` float64 densities in the events'
        order, and each touched pixel's key with its decayed count and time after its last
        event (the new state's entries).
    """
    width, height, _ = _padded(settings)
    n = events.num_events
    tau = settings.tau
    planes = 2 * width * height
    if (planes + 1) * (n + 1) >= _INT64_LIMIT:
        raise ValueError(f"a chunk of {n} events on a {settings.sensor_size[:2]} sensor is too "
                         "long for the density's int64 search keys; feed it in shorter chunks")
    # Grouped by pixel and polarity, stream order kept within a group.
    key, order = stable_sort_small(_pixel_keys(events, settings), planes)
    t = take(events.t, order)
    starts = changes(key)
    first_at = where_true(starts)
    carry = state if state is not None and state.seen else None  # None: nothing carried
    initial = None
    if carry is not None:
        group_key = take(key, first_at)
        carried = take(carry.decayed, group_key)
        initial = carried * _decay(take(t, first_at) - take(carry.last_t, group_key), tau)
        initial.masked_fill_(carried == 0, 0.0)
    counts = _decayed_counts(t, starts, first_at, initial, tau)
    # Search keys (key, stream position) ascend through the grouped events, and so do the
    # queries of one neighbour offset (the key shifts by a constant): cheap searches. A
    # sentinel in front answers the queries that precede every event (its key is -1).
    search = torch.cat([key.new_tensor([-1]), key * n + order])
    key = torch.cat([key.new_tensor([-1]), key])
    t = torch.cat([t[:1], t])
    counts = torch.cat([counts.new_zeros(1), counts])
    density = torch.zeros(n, dtype=torch.float64, device=events.device)
    offsets = patch_offsets(settings.k)
    group = max(1, min(len(offsets), LOOKUP_ELEMENTS // n))
    place = None  # each event's place among the grouped ones, in stream order (compiled)
    if use_compiled(key):
        from evdown_torch.transforms.functional.compiled import density as compiled_density

        place = torch.empty_like(order).index_copy_(0, order, torch.arange(n))
    for begin in range(0, len(offsets), group):
        part = offsets[begin:begin + group]
        shift = torch.tensor([dy * width + dx for dx, dy, _ in part],
                             device=events.device).unsqueeze(1)
        neighbour = key[1:] + shift
        # The neighbour's last event at or before this one in the stream (or the sentinel).
        if place is not None:  # a compiled sweep in stream order: the same where it exists
            at = compiled_density.last_neighbours(key[1:], place, shift.reshape(-1),
                                                  planes).reshape(-1)
        else:
            at = searchsorted_ascending(search, (search[1:] + shift * n).reshape(-1),
                                        right=True)
            at -= 1
        found = take(key, at).reshape(neighbour.shape) == neighbour
        elapsed = t[1:] - take(t, at).reshape(neighbour.shape)
        value = take(counts, at).reshape(neighbour.shape) * _decay(elapsed, tau)
        if carry is not None:  # pixels whose last event came in an earlier chunk
            flat = neighbour.reshape(-1)
            carried = take(carry.decayed, flat).reshape(neighbour.shape)
            late = carried * _decay(t[1:] - take(carry.last_t, flat).reshape(neighbour.shape),
                                    tau)
            value = torch.where(found, value, late.masked_fill_(carried == 0, 0.0))
        else:
            value.masked_fill_(~found, 0.0)
        for row, (_, _, weight) in zip(value, part, strict=True):
            density.add_(row, alpha=weight)
    lasts = last_of_runs(first_at, n) + 1
    in_order = torch.empty_like(density).index_copy_(0, order, density)
    return in_order, (take(key, lasts), take(counts, lasts), take(t, lasts))


def event_density(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    tau: float = 30_000.0,
    k: int = 7,
) -> Tensor:
    """Each event's local density (docs/semantics.md, method 9), in stable time order.

    Args:
        events: ``N`` events (any order; taken in stable time order).
        sensor_size: ``(W, H, P)``.
        tau: decay time constant, in the stream's time unit.
        k: patch side, odd.

    Returns:
        ``(N,)`` float64 densities (each at least 1) of the events sorted stably by ``t``.

    Example:
        Two ON events at one pixel 10 us apart, tau = 10 us: the second sees ``1 + e**-1``.

        >>> ev = Events.from_columns([1, 1], [1, 1], [0, 10], [1, 1])
        >>> [round(d, 4) for d in event_density(ev, sensor_size=(3, 3, 2), tau=10.0,
        ...                                     k=1).tolist()]
        [1.0, 1.3679]
    """
    settings = DensitySettings(sensor_size, (1, 1), tau, k)  # the density needs no factor
    events = sort_by_time(events)
    if events.num_events == 0:
        return torch.empty(0, dtype=torch.float64, device=events.device)
    state: DensityState | None = None
    parts = []
    bounds = chunk_bounds(events.t)
    for start, stop in zip(bounds[:-1], bounds[1:]):
        piece = events.part(start, stop)
        density, touched = _density_sorted(piece, settings, state)
        if len(bounds) > 2:
            state = _next_state(state, settings, piece, touched)
        parts.append(density)
    return torch.cat(parts)


def density_init(settings: DensitySettings, events: Events) -> DensityState:
    """DensitySubsampling's ``init_state``: no pixel has a count; the clock starts at ``t[0]``."""
    width, height, _ = _padded(settings)
    zeros = torch.zeros(2 * width * height, dtype=torch.float64, device=events.device)
    return DensityState(zeros, torch.zeros(zeros.shape[0], dtype=events.t.dtype,
                                           device=events.device), 0, events.t[0].item())


def _next_state(state: DensityState | None, settings: DensitySettings, events: Events,
                touched: tuple[Tensor, Tensor, Tensor]) -> DensityState:
    """The state after ``events`` (the chunk ``touched`` came from)."""
    if state is None:
        state = density_init(settings, events)
    keys, counts, times = touched
    decayed, last_t = state.decayed.clone(), state.last_t.clone()
    decayed[keys] = counts
    last_t[keys] = times
    return DensityState(decayed, last_t, state.seen + events.num_events, state.origin)


def _kept(events: Events, density: Tensor, settings: DensitySettings, seen: int,
          origin: int | float) -> Events:
    """The events whose draw is below ``s * density``, downsampled."""
    draws = chunk_uniforms(events, settings.seed, seen=seen, origin=origin)
    kept = events.select(draws < density.mul_(settings.s))
    return to_regions(kept, settings.factor)


def _step_sorted(
    events: Events, state: DensityState, settings: DensitySettings
) -> tuple[Events, DensityState]:
    """One piece of time-sorted events: the kept ones, downsampled, and the next state."""
    density, touched = _density_sorted(events, settings, state)
    kept = _kept(events, density, settings, state.seen, state.origin)
    return kept, _next_state(state, settings, events, touched)


def density_step(
    events: Events, state: DensityState, settings: DensitySettings
) -> tuple[Events, DensityState]:
    """DensitySubsampling's ``step``: one time-sorted chunk, every event decided by it.

    Each pixel's decayed count and last time carry over in the state; a long chunk goes
    through in pieces (:func:`.protocol.step_in_pieces`), as a session would feed it. On the
    CPU one compiled loop decides the chunk's events in stream order
    (:func:`.compiled.density.decide_in_order`: the same events), unless it leaves the chunk
    to this kernel.
    """
    if use_compiled(events.t):
        result = _compiled_step(events, state, settings)
        if result is not None:
            return result
    return step_in_pieces(events, state, settings, _step_sorted)


@functools.cache
def _patch_columns(k: int, padded_width: int) -> tuple[Tensor, Tensor]:
    """The patch's key offsets on a padded sensor ``padded_width`` keys wide, and its weights.

    ``(k * k,)`` int64 and float64 CPU tensors, in :func:`patch_offsets`' order; shared
    between calls, never written.
    """
    offsets = patch_offsets(k)
    shifts = torch.tensor([dy * padded_width + dx for dx, dy, _ in offsets])
    return shifts, torch.tensor([w for _, _, w in offsets], dtype=torch.float64)


def _compiled_step(events: Events, state: DensityState, settings: DensitySettings
                   ) -> tuple[Events, DensityState] | None:
    """:func:`density_step` by the compiled loop, or ``None`` where it leaves the chunk here."""
    from evdown_torch.transforms.functional.compiled import density as compiled

    n = events.num_events
    draws = chunk_uniforms(events, settings.seed, seen=state.seen, origin=state.origin)
    padded_width, _, radius = _padded(settings)
    shifts, weights = _patch_columns(settings.k, padded_width)
    result = compiled.decide_in_order(
        events, state.decayed, state.last_t, draws, sensor_size=settings.sensor_size,
        factor=settings.factor, tau=settings.tau, s=settings.s, radius=radius,
        shifts=shifts, weights=weights, axis=axis_weights(settings.k), clock_start=state.origin)
    if result is None:
        return None
    kept, decayed, last_t = result
    return kept, DensityState(decayed, last_t, state.seen + n, state.origin)


def density_whole(events: Events, settings: DensitySettings) -> Events:
    """The whole stream (any order): one step from a fresh state, or a short one's densities.

    A long stream, or any on the CPU's compiled path, goes through :func:`density_step`; a
    short one elsewhere without the per-pixel state.
    """
    events = sort_by_time(events)
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device)
    if len(chunk_bounds(events.t)) > 2 or use_compiled(events.t):
        return density_step(events, density_init(settings, events), settings)[0]
    density, _ = _density_sorted(events, settings, None)
    return _kept(events, density, settings, 0, events.t[0].item())


def density_subsampling(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    tau: float = 30_000.0,
    k: int = 7,
    s: float = 1.0,
    seed: int = 0,
) -> Events:
    """DensitySubsampling (docs/semantics.md, method 9) of a whole stream, then Downsample.

    Args:
        events: ``N`` events (any order).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        tau: decay time constant of the per-pixel counts, in the stream's time unit.
        k: patch side, odd.
        s: the budget setting: keep an event iff its draw ``u_e < s * density``.
        seed: mixed into every event's draw.

    Returns:
        The kept events, downsampled, sorted by ``t``.

    Example:
        >>> ev = Events.from_columns([0, 1, 2, 3], [0, 1, 2, 3], [0, 5, 9, 12], [1, 1, 0, 1])
        >>> density_subsampling(ev, sensor_size=(4, 4, 2), factor=(2, 2), s=1.0).x.tolist()
        [0, 0, 1, 1]
    """
    return density_whole(events, DensitySettings(sensor_size, factor, tau, k, s, seed))


#: DensitySubsampling's kernels (:class:`~evdown_torch.DensitySubsampling`): causal.
DENSITY: Method[DensitySettings, DensityState] = Method(
    density_init, density_step, whole=density_whole
)
