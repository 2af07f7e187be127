"""PoissonSubsampling kernel (docs/semantics.md, method 10): a probability map under a budget cap.

Time is cut in windows of ``window`` from the stream's first timestamp. Per polarity, the
events of window ``m`` at pixel ``j`` number ``n_j``; the next window keeps an event at ``j``
with probability ``P(j) = min(1, alpha * B(j) / mean B)``, ``B`` the Gaussian blur (sigma 2,
truncated at 3 sigma, renormalised at the edges) of ``1 - exp(-n_j)`` (``P = alpha`` in the
first window and where ``mean B = 0``), and a running cap refuses an event whenever keeping
it would make ``kept > alpha * seen``. Kept events are then downsampled. Causal.

How it is computed, without a loop over events or dense per-window maps:

* **Counts** of the windows a chunk needs (its own and each one's predecessor) form a sparse
  table keyed by (window, polarity, pixel): only pixels with events have entries.
* **B at an event's pixel** gathers the predecessor window's counts over the 13 x 13
  neighbourhood, one binary search in the table per neighbour, added in a fixed order; the
  edge renormalisation is a product of a column and a row factor, as the truncated Gaussian
  is separable. **mean B** over the sensor is ``sum_i (1 - exp(-n_i)) * M_i / (W * H)`` over
  the entries ``i``, where ``M_i`` (also separable) is the total weight pixel ``i`` spreads
  over the sensor: its cost is the entries', not the sensor's.
* **Distinct keys** (the windows, the table's entries, the blur's targets) come from a table
  of marks over their range where it is small next to them (:data:`MARKS_PER_VALUE`; a
  chunk's keys span a few windows of the sensor), else from ``torch.unique``'s sort: the same
  sorted values and inverse either way; the blur's lookups of its targets, likewise, from a
  table of their places, else by binary search.
* **The cap** is exact in integers: with ``alpha`` taken as the fraction ``a / b`` nearest it
  (``b <= 10**6``), ``L_e = floor(a * seen_e / b)`` is the most that may be kept after ``e``.
  A candidate is kept iff the count stays within ``L``, so the kept count after ``e`` is
  ``K_e = min(K_{e-1} + c_e, L_e)`` (``c_e``: the draw is below ``P``), which unrolls to
  ``K_e = C_e + min(K_0, min_{i <= e} (L_i - C_i))`` with ``C`` the running count of
  candidates: a cumulative sum and a cumulative minimum.
* **A stream** carries the first timestamp, the events seen and kept, and the table entries
  of its last window and the one before (:class:`PoissonState`: bounded by the sensor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from functools import cache, lru_cache
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import (
    distinct_in_range,
    divide,
    searchsorted_ascending,
    take,
    where_true,
)
from evdown_torch.checks import check_non_negative_int, check_positive_float
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.downsample import to_regions
from evdown_torch.transforms.functional.draws import chunk_uniforms
from evdown_torch.transforms.functional.protocol import Method, run_protocol, step_in_pieces
from evdown_torch.transforms.functional.settings import RegionSettings
from evdown_torch.transforms.functional.temporal import bin_index

__all__ = [
    "POISSON",
    "BLUR_RADIUS",
    "BLUR_SIGMA",
    "PoissonSettings",
    "PoissonState",
    "poisson_init",
    "poisson_step",
    "poisson_subsampling",
]

#: The blur's standard deviation, in pixels, and its truncation (3 sigma).
BLUR_SIGMA = 2.0
BLUR_RADIUS = 6

#: Elements of the temporaries of one group of neighbour lookups (events x neighbours).
LOOKUP_ELEMENTS = 1 << 20

#: Largest denominator of the fraction that stands for ``alpha`` in the cap.
MAX_DENOMINATOR = 10**6


@dataclass(frozen=True)
class PoissonSettings(RegionSettings):
    """PoissonSubsampling's settings, checked once.

    Attributes:
        window: window length in the stream's time unit (microseconds for Tonic), > 0; a
            whole number for integer timestamps (checked at call time).
        alpha: the budget setting, the fraction of events kept, in ``[1e-6, 1]``; the cap
            uses the fraction with denominator at most ``10**6`` nearest it (so decimal
            budgets such as 0.05 are exact).
        seed: non-negative integer mixed into every event's draw.
    """

    window: float = 6_000.0
    alpha: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive_float("window", self.window)
        alpha = check_positive_float("alpha", self.alpha)
        if not 1e-6 <= alpha <= 1.0:
            raise ValueError(f"alpha must lie in [1e-6, 1] (a fraction of the events), "
                             f"got {alpha!r}")
        object.__setattr__(self, "alpha", alpha)
        object.__setattr__(self, "seed", check_non_negative_int("seed", self.seed))

    @property
    def alpha_fraction(self) -> Fraction:
        """``alpha`` as the fraction ``a / b`` (``b <= 10**6``) nearest it."""
        return Fraction(self.alpha).limit_denominator(MAX_DENOMINATOR)


class PoissonState(NamedTuple):
    """A PoissonSubsampling stream between chunks (bounded by the sensor).

    Attributes:
        origin: the stream's first timestamp (windows start there).
        seen: events seen so far.
        kept: events kept so far.
        windows: ``(E,)`` int64 window of each count entry (the last window and the one
            before it).
        keys: ``(E,)`` int64 pixel and polarity of each entry, ``(p * H + y) * W + x``.
        counts: ``(E,)`` int64 events of that pixel and polarity in that window.
    """

    origin: int | float
    seen: int
    kept: int
    windows: Tensor
    keys: Tensor
    counts: Tensor


@cache
def _blur_weights() -> tuple[float, ...]:
    """The 1-D Gaussian's weights at ``-BLUR_RADIUS .. BLUR_RADIUS``."""
    return tuple(math.exp(-d * d / (2 * BLUR_SIGMA**2)) for d in range(-BLUR_RADIUS,
                                                                        BLUR_RADIUS + 1))


@lru_cache(maxsize=16)
def _edge_factors(size: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """Per coordinate along one axis of ``size`` pixels: ``(norm, spread)`` (shared, never written).

    ``norm[j]``: the weight inside the sensor of the window around ``j`` (what ``B(j)`` is
    divided by); ``spread[i] = sum_j g(j - i) / norm[j]``: what pixel ``i`` adds to the sum of
    ``B`` per unit of its value. Both are per axis; the 2-D ones are products.
    """
    g = torch.tensor(_blur_weights(), dtype=torch.float64, device=device)
    coords = torch.arange(size, device=device)
    shifts = torch.arange(-BLUR_RADIUS, BLUR_RADIUS + 1, device=device)
    other = coords.unsqueeze(1) + shifts  # (size, 13): j + d
    inside = (other >= 0) & (other < size)
    norm = (g * inside).sum(1)
    spread = (g * inside / take(norm, other.clamp(0, size - 1).reshape(-1))
              .reshape(other.shape)).sum(1)
    return norm, spread


#: Most marks per value for which :func:`_distinct` marks the values' range in a table rather
#: than sorting them (``torch.unique``), and :func:`_places` tabulates their places rather
#: than searching them: the live replay's chunks (a few windows of a 128x128 sensor, 240,000
#: events) spent 23 ms a chunk in the sorts. A few thousand marks more are always allowed.
MARKS_PER_VALUE = 4
MARKS_SLACK = 4096


def _marks_fit(low: int, high: int, n: int) -> bool:
    """Whether a table over ``low .. high`` is small next to ``n`` values.

    At most :data:`MARKS_PER_VALUE` entries per value, and :data:`MARKS_SLACK` more.
    """
    return high - low < MARKS_PER_VALUE * n + MARKS_SLACK


def _distinct(values: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.unique(values, return_inverse=True)`` of int64 ``values``: sorted, and each's.

    By a table of marks over ``min .. max`` where it is small (:func:`_marks_fit`), else by
    the sort.

    Example:
        >>> _distinct(torch.tensor([7, 3, 7, 5]))
        (tensor([3, 5, 7]), tensor([2, 0, 2, 1]))
    """
    if values.shape[0]:
        low, high = (int(bound) for bound in torch.aminmax(values))
        if _marks_fit(low, high, values.shape[0]):
            return distinct_in_range(values, low, high)
    distinct, inverse = torch.unique(values, return_inverse=True)
    return distinct, inverse


def _places(ordered: Tensor) -> tuple[int, Tensor | None]:
    """The places of sorted distinct int64 ``ordered``, by value: ``(low, place)``.

    ``place[v - low]`` is the index of ``v`` in ``ordered`` (-1 for a value between them): a
    table over their range where it is small next to them (:func:`_marks_fit`); ``(0, None)``
    where it is not (search them instead).

    Example:
        >>> _places(torch.tensor([4, 6, 7]))
        (4, tensor([ 0, -1,  1,  2]))
    """
    if not ordered.shape[0]:
        return 0, None
    low, high = int(ordered[0]), int(ordered[-1])
    if not _marks_fit(low, high, ordered.shape[0]):
        return 0, None
    place = torch.full((high - low + 1,), -1, dtype=torch.int64, device=ordered.device)
    place[ordered - low] = torch.arange(ordered.shape[0], device=ordered.device)
    return low, place


def _entries(windows: Tensor, keys: Tensor, counts: Tensor, planes: int
             ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The distinct (window, key) entries, sorted, with their summed counts.

    Returns:
        ``(distinct windows, search keys, counts, inverse)``: the windows present, each
        entry's ``rank * planes + key`` (``rank``: its window's place among them), each
        entry's count, and each input row's entry.
    """
    distinct, _ = _distinct(windows)
    if distinct.shape[0] * planes >= 1 << 62:
        raise ValueError("a chunk spans too many windows for the int64 search keys; feed it "
                         "in shorter chunks")
    rank = torch.searchsorted(distinct, windows)
    search, inverse = _distinct(rank * planes + keys)
    total = torch.zeros(search.shape[0], dtype=torch.int64, device=keys.device)
    total.index_add_(0, inverse, counts)
    return distinct, search, total, inverse


def _row_blur(search: Tensor, value: Tensor, x: Tensor, width: int) -> tuple[Tensor, Tensor]:
    """The blur along rows of the sparse map ``value`` at ``search``: ``(targets, sums)``.

    Every entry spreads ``g(dx) * value`` to the pixel ``dx`` columns away (inside the
    sensor); the sums are gathered per target pixel, each in the order of ``dx``.
    """
    g = torch.tensor(_blur_weights(), dtype=torch.float64, device=value.device)
    dx = torch.arange(-BLUR_RADIUS, BLUR_RADIUS + 1, device=value.device).unsqueeze(1)
    inside = where_true(((x + dx >= 0) & (x + dx < width)).reshape(-1))  # (in order)
    target = take((search + dx).reshape(-1), inside)
    spread = take((g.unsqueeze(1) * value).reshape(-1), inside)
    targets, inverse = _distinct(target)
    sums = torch.zeros(targets.shape[0], dtype=torch.float64, device=value.device)
    return targets, sums.index_add_(0, inverse, spread)


def _probabilities(
    events: Events, window: Tensor, key: Tensor, state: PoissonState,
    settings: PoissonSettings,
) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]]:
    """Each event's keep probability ``P``, and the chunk's count table.

    ``B`` and ``mean B`` are computed once per table entry (pixel, polarity and window)
    and handed to the entry's events.

    Returns:
        ``(P, (distinct windows, search keys, counts))``.
    """
    width, height, _ = settings.sensor_size
    planes = 2 * width * height
    device = events.device
    n = events.num_events
    distinct, search, total, inverse = _entries(
        torch.cat([state.windows, window]), torch.cat([state.keys, key]),
        torch.cat([state.counts, torch.ones(n, dtype=torch.int64, device=device)]), planes)
    rank, entry_key = divide(search, planes), search % planes
    entry_x = entry_key % width
    entry_y = divide(entry_key, width) % height
    entry_p = divide(entry_key, width * height)
    norm_x, spread_x = _edge_factors(width, device)
    norm_y, spread_y = _edge_factors(height, device)
    value = -torch.expm1(-total.to(torch.float64))  # 1 - exp(-n)
    # mean B of each window and polarity: what every entry spreads over the sensor.
    mass = torch.zeros(2 * distinct.shape[0], dtype=torch.float64, device=device)
    mass.index_add_(0, rank * 2 + entry_p,
                    value * take(spread_x, entry_x) * take(spread_y, entry_y))
    # Each entry's previous window among the table's (its rank, if that window is there).
    before = torch.searchsorted(distinct, take(distinct, rank) - 1)
    safe_before = before.clamp(max=distinct.shape[0] - 1)
    present = take(distinct, safe_before) == take(distinct, rank) - 1
    mean = take(mass, safe_before * 2 + entry_p) / (width * height)
    mean.masked_fill_(~present, 0.0)
    # B at each entry's pixel from the previous window: the blur along rows, then columns
    # gathered at the entry (the Gaussian is separable). The queries of one row offset
    # ascend with the entries.
    rows, row_sums = _row_blur(search, value, entry_x, width)
    base = safe_before * planes + entry_key
    blurred = torch.zeros(search.shape[0], dtype=torch.float64, device=device)
    last = rows.shape[0] - 1
    low, place = _places(rows)
    for dy, weight in zip(range(-BLUR_RADIUS, BLUR_RADIUS + 1), _blur_weights(), strict=True):
        wanted = base + dy * width
        if place is None:
            at = searchsorted_ascending(rows, wanted).clamp_(max=last)
        else:  # the row's place where it is one of rows (else a row that is not it)
            at = take(place, (wanted - low).clamp_(0, place.shape[0] - 1)).clamp_(min=0)
        found = (take(rows, at) == wanted) & (entry_y + dy >= 0) & (entry_y + dy < height)
        blurred.add_(take(row_sums, at).masked_fill_(~found, 0.0), alpha=weight)
    blurred /= take(norm_x, entry_x) * take(norm_y, entry_y)
    spread = mean > 0
    ratio = blurred / torch.where(spread, mean, 1.0)
    probability = torch.where(spread, (settings.alpha * ratio).clamp_(max=1.0), settings.alpha)
    event_entry = inverse[state.windows.shape[0]:]
    return take(probability, event_entry), (distinct, search, total)


def _capped(candidate: Tensor, seen: int, kept: int, alpha: Fraction) -> Tensor:
    """Which candidates the running cap ``kept <= alpha * seen`` lets through (exact)."""
    n = candidate.shape[0]
    a, b = alpha.numerator, alpha.denominator
    if a * (seen + n) >= 1 << 62:
        raise ValueError(f"{seen + n} events are too many for the cap's exact int64 "
                         f"arithmetic at alpha = {a}/{b}")
    seen_after = torch.arange(seen + 1, seen + n + 1, device=candidate.device)
    limit = divide(seen_after * a, b)
    running = torch.cumsum(candidate.to(torch.int64), 0)
    slack = torch.cummin(limit - running, 0).values.clamp_(max=kept)
    total = running + slack
    previous = torch.cat([total.new_tensor([kept]), total[:-1]])
    return total > previous


def _step_sorted(
    events: Events, state: PoissonState, settings: PoissonSettings
) -> tuple[Events, PoissonState]:
    """:func:`poisson_step` on one piece of time-sorted events."""
    width, height, _ = settings.sensor_size
    planes = 2 * width * height
    n = events.num_events
    window = bin_index(events.t, dt=settings.window, t_start=state.origin)
    key = (events.p.to(torch.int64) * height + events.y) * width + events.x
    probability, (distinct, search, total) = _probabilities(events, window, key, state,
                                                            settings)
    draws = chunk_uniforms(events, settings.seed, seen=state.seen, origin=state.origin)
    keep = _capped(draws < probability, state.seen, state.kept, settings.alpha_fraction)
    kept = events.select(keep)
    # The entries of the last window and the one before it carry over.
    entry_window = take(distinct, divide(search, planes))
    recent = entry_window >= window[-1] - 1
    new_state = PoissonState(state.origin, state.seen + n, state.kept + kept.num_events,
                             entry_window[recent], (search % planes)[recent], total[recent])
    return to_regions(kept, settings.factor), new_state


def poisson_init(settings: PoissonSettings, events: Events) -> PoissonState:
    """PoissonSubsampling's ``init_state``: windows start at ``t[0]``, nothing counted."""
    empty = torch.empty(0, dtype=torch.int64, device=events.device)
    return PoissonState(events.t[0].item(), 0, 0, empty, empty.clone(), empty.clone())


def poisson_step(
    events: Events, state: PoissonState, settings: PoissonSettings
) -> tuple[Events, PoissonState]:
    """PoissonSubsampling's ``step``: one time-sorted chunk, every event decided by it.

    The counts of the last two windows and the cap's tallies carry over in the state; a long
    chunk goes through in pieces (:func:`.protocol.step_in_pieces`).
    """
    if use_compiled(events.t):
        result = _compiled_step(events, state, settings)
        if result is not None:
            return result
    return step_in_pieces(events, state, settings, _step_sorted)


def _compiled_step(events: Events, state: PoissonState, settings: PoissonSettings
                   ) -> tuple[Events, PoissonState] | None:
    """:func:`poisson_step` by the compiled loop, or ``None`` where it leaves the chunk here."""
    from evdown_torch.transforms.functional.compiled import poisson as compiled

    n = events.num_events
    fraction = settings.alpha_fraction
    a, b = fraction.numerator, fraction.denominator
    if a * (state.seen + n) >= 1 << 62:
        return None  # (the eager kernel says why)
    width, height, _ = settings.sensor_size
    window = bin_index(events.t, dt=settings.window, t_start=state.origin)
    draws = chunk_uniforms(events, settings.seed, seen=state.seen, origin=state.origin)
    result = compiled.decide_in_order(
        events, window, draws, state.windows, state.keys, state.counts,
        sensor_size=settings.sensor_size, factor=settings.factor, alpha=settings.alpha,
        fraction=(a, b), seen=state.seen, kept=state.kept, blur=_blur_weights(),
        edges=(*_edge_factors(width, events.device), *_edge_factors(height, events.device)))
    if result is None:
        return None
    kept, kept_count, windows, keys, counts = result
    return kept, PoissonState(state.origin, state.seen + n, kept_count, windows, keys, counts)


def poisson_subsampling(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    window: float = 6_000.0,
    alpha: float = 1.0,
    seed: int = 0,
) -> Events:
    """PoissonSubsampling (docs/semantics.md, method 10) of a whole stream, then Downsample.

    Args:
        events: ``N`` events (any order).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        window: window length in the stream's time unit (a whole number for integer ``t``).
        alpha: the budget setting, the fraction of events kept, in ``[1e-6, 1]``.
        seed: mixed into every event's draw.

    Returns:
        The kept events, downsampled, sorted by ``t``.

    Example:
        The cap at alpha = 1/2 keeps at most half of the events seen so far, so the first
        event (in the first window, drawn against ``P = 1/2``) may be kept only if its
        draw allows and 1 <= 1/2 * 1 does not hold: it never is.

        >>> ev = Events.from_columns([0, 1, 2, 3], [0, 0, 0, 0], [0, 1, 2, 3], [1, 1, 1, 1])
        >>> out = poisson_subsampling(ev, sensor_size=(4, 1, 2), factor=(1, 1), alpha=0.5)
        >>> 0 not in out.t.tolist(), out.num_events <= 2
        (True, True)
    """
    return run_protocol(POISSON, PoissonSettings(sensor_size, factor, window, alpha, seed), events)


#: PoissonSubsampling's kernels (:class:`~evdown_torch.PoissonSubsampling`): causal.
POISSON: Method[PoissonSettings, PoissonState] = Method(poisson_init, poisson_step)
