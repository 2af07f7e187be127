"""The DVS reference rule and region grouping, shared by the log-luminance kernels.

A downscaled pixel watches a level ``M(t)`` with contrast threshold ``theta`` and keeps a
reference index ``q``: it emits ON and increments ``q`` whenever ``M`` reaches
``theta * (q + 1)``, OFF and decrements whenever ``M`` reaches ``theta * (q - 1)``.

The kernels sample ``M`` at the end of monotone *moves* (one input event for EventCount, one
monotone piece of the interpolated curve for the linear and cubic methods). Write
``u = M / theta`` at the end of a move. After the move, ``q`` always lies in
``[floor(u), ceil(u)]``:

* on a level (``u`` an integer), ``q = u``;
* strictly inside a cell ``(m, m + 1)``, ``q`` is ``m + 1`` if the walk entered the cell from
  above and ``m`` if it entered from below, and it keeps that value while it stays in the cell.

So ``q`` after every move follows from each move's ``(floor(u), u is an integer)`` and its
predecessor's, with a forward fill over runs of moves in one cell: no sequential scan. This is
the clamp recurrence ``q_k = clamp(q_{k-1}, floor(u_k), ceil(u_k))`` solved in closed form.

This module is the rule's one home: the exact level test (:func:`level_index`), the value of a
level (:func:`level_value`), the reference index (:func:`reference_index`) and its crossings
(:func:`crossings`, :func:`move_crossings`), used by the kernels and the synthetic pixel
model (whose two-threshold variant, for the synthetic pixels, is
:mod:`evdown_torch.synthetic.two_thresholds`).
"""

from __future__ import annotations

from fractions import Fraction
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import (
    changes,
    last_of_runs,
    narrow_dtype,
    runs_of,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.checks import check_output_count, output_size

__all__ = [
    "MAX_DENOMINATOR",
    "SNAP",
    "Crossings",
    "RegionGroups",
    "RegionRuns",
    "capped_threshold",
    "crossings",
    "group_by_region",
    "level_index",
    "level_value",
    "move_crossings",
    "moves_to_solve",
    "reference_index",
    "region_dtype",
    "region_runs",
    "rule_crossings",
    "threshold_fraction",
]

#: A region level within this many thresholds of a level is on it (see :func:`level_index`).
SNAP = 1e-9

#: Largest denominator of the rational that stands for ``threshold`` (0.01 is 1/100 exactly).
MAX_DENOMINATOR = 1_000_000


def threshold_fraction(threshold: float) -> Fraction:
    """The rational ``a / b`` (``b <= 10**6``) nearest to ``threshold``, used for exact tests.

    Example:
        >>> threshold_fraction(0.01), threshold_fraction(2.5)
        (Fraction(1, 100), Fraction(5, 2))
    """
    fraction = Fraction(threshold).limit_denominator(MAX_DENOMINATOR)
    if fraction <= 0:
        raise ValueError(f"threshold must be positive and at least 1e-6, got {threshold!r}")
    return fraction


def capped_threshold(fraction: Fraction, bound: int) -> Fraction:
    """``fraction``, or ``bound + 1`` when it is larger, for levels ``|M| <= bound``.

    Above every reachable ``|M|`` only level 0 can be crossed: every such threshold gives the
    same ``floor(M / theta)`` (-1 below 0, else 0) and the same on-level test (``M == 0``),
    hence the same events. Capping keeps the exact integer arithmetic inside int64 for
    thresholds as large as 1e300.

    Example:
        >>> capped_threshold(Fraction(10**300), 7), capped_threshold(Fraction(1, 2), 7)
        (Fraction(8, 1), Fraction(1, 2))
    """
    return fraction if fraction <= bound else Fraction(bound + 1)


def region_dtype(sensor_size: tuple[int, int, int], factor: tuple[int, int],
                 regions: int) -> torch.dtype:
    """The narrowest integer type of a chunk's coordinates and region ids.

    ``regions`` counts the regions of all the stacked recordings (int16 up to 32,768 for a
    sensor that fits too).

    Example:
        >>> region_dtype((128, 128, 2), (4, 4), 32 * 32)
        torch.int16
    """
    out_w = output_size(sensor_size, factor)[0]
    return narrow_dtype(max(out_w * factor[0], regions // out_w * factor[1], regions))


class RegionRuns(NamedTuple):
    """Where each region's events lie once the events are grouped by region.

    Attributes:
        touched: ``(R',)`` int64 ids of the regions with events, ascending.
        firsts: ``(R',)`` int64 position of each touched region's first grouped event.
        lasts: ``(R',)`` int64 position of its last.
        first: ``(N,)`` bool, the grouped event is its region's first.
    """

    touched: Tensor
    firsts: Tensor
    lasts: Tensor
    first: Tensor


def region_runs(region: Tensor, regions: int) -> RegionRuns:
    """The runs of sorted region ids ``region`` (``(N,)``, ids below ``regions``).

    By bisection for every region id when the events outnumber the regions; from the run
    starts of ``region`` when they do not (a live stream's small chunk, whose cost would
    otherwise follow the sensor's regions rather than its events). Both give the same runs.

    Example:
        >>> runs = region_runs(torch.tensor([0, 0, 2, 3, 3, 3]), 5)
        >>> runs.touched.tolist(), runs.firsts.tolist(), runs.lasts.tolist()
        ([0, 2, 3], [0, 2, 3], [1, 2, 5])
        >>> region_runs(torch.tensor([0, 0, 2, 3, 3, 3]), 9).lasts.tolist()
        [1, 2, 5]
    """
    n = region.shape[0]
    if n < regions:
        first = changes(region)
        firsts = where_true(first)
        return RegionRuns(take(region, firsts).to(torch.int64), firsts,
                          last_of_runs(firsts, n), first)
    ids = torch.arange(regions, dtype=region.dtype, device=region.device)
    edges = torch.cat([torch.searchsorted(region, ids), ids.new_tensor([n], dtype=torch.int64)])
    touched = where_true(edges[1:] > edges[:-1])
    firsts = take(edges, touched)
    lasts = take(edges[1:], touched) - 1
    first = torch.zeros(n, dtype=torch.bool, device=region.device).index_fill_(0, firsts, True)
    return RegionRuns(touched, firsts, lasts, first)


class RegionGroups(NamedTuple):
    """Events (already in time order) grouped by output region, time order kept inside groups.

    Attributes:
        order: ``(N,)`` int64, position in time order of each grouped event.
        region: ``(N,)`` int64 region id ``ry * Wo + rx`` of each grouped event.
        first: ``(N,)`` bool, the event is its region's first.
    """

    order: Tensor
    region: Tensor
    first: Tensor


def group_by_region(rx: Tensor, ry: Tensor, out_width: int) -> RegionGroups:
    """Stable grouping of time-ordered events by region.

    Args:
        rx: ``(N,)`` int64 region column of each event, in time order.
        ry: ``(N,)`` int64 region row of each event, in time order.
        out_width: ``Wo``, the output sensor width.

    Returns:
        The :class:`RegionGroups`.
    """
    region_id = ry * out_width
    region_id += rx
    region, order = stable_sort_small(region_id)
    return RegionGroups(order, region, changes(region))


def reference_index(floor_u: Tensor, on_level: Tensor, first: Tensor, q_start: Tensor) -> Tensor:
    """Reference index ``q`` after each move, for moves grouped by region in time order.

    Args:
        floor_u: ``(N,)`` int64 ``floor(M / theta)`` at the end of each move.
        on_level: ``(N,)`` bool, ``M / theta`` is an integer at the end of the move.
        first: ``(N,)`` bool, the move is the first of its region.
        q_start: ``(N,)`` int64, the region's ``q`` before its first move (read where
            ``first``), or a 0-d int64 tensor for all regions (0 for fresh pixels).

    Returns:
        ``(N,)`` int64 reference index after each move.

    Example:
        >>> import torch
        >>> u = torch.tensor([0.5, 1.0, 0.5, -0.5, 0.5])  # M / theta after each move
        >>> fl = torch.floor(u).long()
        >>> first = torch.tensor([True, False, False, False, False])
        >>> reference_index(fl, u == fl, first, torch.tensor(0)).tolist()
        [0, 1, 1, 0, 0]
    """
    if floor_u.shape[0] == 0:
        return floor_u.clone()
    prev_floor = floor_u.roll(1)
    # A run of moves sharing one value starts at a region's first move, on a level, right
    # after a level, or on entering another cell; element 0 is always a region's first.
    starts = prev_floor != floor_u
    starts |= on_level
    starts |= on_level.roll(1)
    starts |= first
    at = where_true(starts)
    m = take(floor_u, at)
    value = m + (take(prev_floor, at) > m)  # entered from above: m + 1; from below: m
    first_at = take(first, at)
    q0 = take(q_start, at) if q_start.ndim else q_start.expand_as(m)
    value = torch.where(first_at, torch.minimum(torch.maximum(q0, m), m + 1), value)
    value = torch.where(take(on_level, at), m, value)
    run = torch.cumsum(starts, 0)
    run -= 1
    return take(value, run)


class Crossings(NamedTuple):
    """Level crossings of all moves, in move order and, inside a move, in time order.

    Attributes:
        move: ``(K,)`` int64 index of the move that crossed the level.
        level: ``(K,)`` int64 level index ``j`` crossed (the level is ``theta * j``).
        on: ``(K,)`` bool, ON (upward) crossing.
    """

    move: Tensor
    level: Tensor
    on: Tensor


def moves_to_solve(
    floor_u: Tensor, on_level: Tensor, first: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """The moves that can change ``q``, with their ``floor(u)`` and on-level flags.

    A move that stays strictly inside the cell its predecessor ended in keeps ``q`` and
    crosses nothing (a tenth or less of the events when a level takes several events to
    cross): ``(kept positions, floor(u), on level)`` of the others, for moves grouped by
    region (``first``: a region's first move) as :func:`reference_index` takes them.

    Example:
        >>> floor_u = torch.tensor([0, 0, 0, 1, 1, 1])
        >>> on_level = torch.tensor([False, False, False, True, False, False])
        >>> first = torch.tensor([True, False, False, False, False, True])
        >>> [v.tolist() for v in moves_to_solve(floor_u, on_level, first)]
        [[0, 3, 4, 5], [0, 1, 1, 1], [False, True, False, False]]
    """
    moved = changes(floor_u)
    moved |= first
    moved |= on_level
    moved[1:] |= on_level[:-1]
    kept = where_true(moved)
    return kept, take(floor_u, kept), take(on_level, kept)


def crossings(q_before: Tensor, q_after: Tensor, *, emitted: int = 0) -> Crossings:
    """Expand each move's change of reference index into one crossing per level.

    A move taking ``q`` from ``a`` to ``b > a`` crosses levels ``a + 1, ..., b`` upward (ON);
    from ``a`` to ``b < a`` it crosses ``a - 1, ..., b`` downward (OFF).

    Args:
        q_before: ``(N,)`` int64 index before each move.
        q_after: ``(N,)`` int64 index after each move.
        emitted: events the call already emitted (earlier chunks of the stream).

    Returns:
        The :class:`Crossings`, ``K = sum |q_after - q_before|``.

    Raises:
        ValueError: when ``emitted + K`` exceeds
            :func:`~evdown_torch.checks.max_output_events` (counted before building them).

    Example:
        >>> import torch
        >>> c = crossings(torch.tensor([0, 2, 2]), torch.tensor([2, 2, 1]))
        >>> c.move.tolist(), c.level.tolist(), c.on.tolist()
        ([0, 0, 2], [1, 2, 1], [True, True, False])
    """
    delta = q_after - q_before
    changed = where_true(delta != 0)
    delta = take(delta, changed)
    count = delta.abs()
    total = int(count.sum())
    check_output_count(emitted + total)
    pick = runs_of(count, total)
    offsets = torch.cumsum(count, 0) - count
    within = torch.arange(pick.shape[0], device=delta.device) - take(offsets, pick)
    on = take(delta, pick) > 0
    base = take(take(q_before, changed), pick)
    level = torch.where(on, base + 1 + within, base - 1 - within)
    return Crossings(take(changed, pick), level, on)


def level_index(
    whole: Tensor, part: Tensor, pixels: Tensor | int, threshold: Fraction
) -> tuple[Tensor, Tensor]:
    """``floor(u)`` and ``u is on a level`` for ``u = (whole + part) / (threshold * pixels)``.

    ``whole + part`` is ``n_r * M_r``: an exact integer part and a float remainder. Where the
    remainder is exactly 0 the test is done in integers (``threshold = a / b`` is rational), so
    a region sitting on a level is seen on it exactly. Elsewhere ``u`` is a float, and a ``u``
    within :data:`SNAP` of an integer counts as on that level: float rounding cannot tell such
    a ``u`` from the level itself, and snapping keeps the result stable when it lands there.

    Args:
        whole: int64 integer part of ``n_r * M_r``.
        part: float64 remainder.
        pixels: ``n_r``, int64 of the shape of ``whole`` or one int for all.
        threshold: ``theta`` as a fraction ``a / b``.

    Returns:
        ``(floor_u, on_level)``, int64 and bool, of the shape of ``whole``.

    Example:
        >>> fl, on = level_index(torch.tensor([3, 3, 1]), torch.tensor([0.0, 0.5, 0.5 - 1e-12]),
        ...                      torch.tensor([2, 2, 2]), Fraction(3, 4))
        >>> fl.tolist(), on.tolist()
        ([2, 2, 1], [True, False, True])
    """
    a, b = threshold.numerator, threshold.denominator
    if isinstance(pixels, int):
        u = (whole.to(torch.float64) + part) * (b / (pixels * a))
    else:
        u = (whole.to(torch.float64) + part) * b / (pixels * a).to(torch.float64)
    nearest = torch.round(u)
    on_level = (u - nearest).abs() <= SNAP
    floor_u = torch.where(on_level, nearest, torch.floor(u)).to(torch.int64)
    exact_at = where_true(part == 0)
    if exact_at.shape[0]:
        numerator = take(whole, exact_at) * b
        denominator = pixels * a if isinstance(pixels, int) else take(pixels, exact_at) * a
        exact_floor = torch.div(numerator, denominator, rounding_mode="floor")
        floor_u.scatter_(0, exact_at, exact_floor)
        on_level.scatter_(0, exact_at, exact_floor * denominator == numerator)
    return floor_u, on_level


def level_value(level: Tensor, pixels: Tensor | int, threshold: Fraction) -> Tensor:
    """``n_r * theta * j`` as float64, the value of ``n_r * M_r`` on level ``j``."""
    a, b = threshold.numerator, threshold.denominator
    return (level * pixels * a).to(torch.float64) / b


def move_crossings(
    floor_u: Tensor, on_level: Tensor, first: Tensor, *, emitted: int = 0,
    q_start: Tensor | None = None, q_first: Tensor | None = None, lands_on_levels: bool = False,
) -> Crossings:
    """The reference rule over monotone moves grouped by region, from ``q = q_start``.

    Applies :func:`~evdown_torch.transforms.functional.reference.reference_index` and
    :func:`~evdown_torch.transforms.functional.reference.crossings` to the moves that can
    change ``q`` only: a move that stays strictly inside the cell its predecessor ended in
    keeps ``q`` and crosses nothing, so dropping it changes no other move's result.

    Args:
        floor_u: ``(S,)`` int64 ``floor(M / theta)`` at the end of each move.
        on_level: ``(S,)`` bool, the move ends on a level.
        first: ``(S,)`` bool, the move is its region's first.
        emitted: events the call already emitted (see :func:`crossings`).
        q_start: ``(S,)`` int64 ``q`` of each move's region before its first move (read
            where ``first``; a resumed stream), or ``None`` for 0 (a fresh one).
        q_first: the same values given once per region instead: ``(F,)`` int64, one for
            each True of ``first`` in order (``q_start`` must then be ``None``).
        lands_on_levels: every move ends on each level it reaches (EventCount with an integer
            threshold: a move changes ``b * S`` by one, the levels are multiples of the integer
            ``a * n_r``). A move that ends off every level then keeps ``q``, so only first
            moves and moves on a level are solved.

    Returns:
        The crossings, with ``move`` indexing the given moves.
    """
    if lands_on_levels:
        kept = where_true(first | on_level)
        floor_k, on_k = take(floor_u, kept), take(on_level, kept)
    else:
        kept, floor_k, on_k = moves_to_solve(floor_u, on_level, first)
    first_k = take(first, kept)
    if q_start is not None:
        q0 = take(q_start, kept)
    else:
        q0 = torch.zeros_like(floor_k)
        if q_first is not None:  # every first move is kept, in order
            q0[first_k] = q_first.to(q0.dtype)
    cross, _ = rule_crossings(floor_k, on_k, first_k, q0, emitted=emitted)
    return Crossings(take(kept, cross.move), cross.level, cross.on)


def rule_crossings(
    floor_u: Tensor, on_level: Tensor, first: Tensor, q_start: Tensor, *, emitted: int = 0
) -> tuple[Crossings, Tensor]:
    """The reference rule over moves grouped by region: their crossings and ``q`` after each.

    Args:
        floor_u: ``(S,)`` int64 ``floor(M / theta)`` at the end of each move.
        on_level: ``(S,)`` bool, the move ends on a level.
        first: ``(S,)`` bool, the move is its region's first.
        q_start: ``(S,)`` int64 ``q`` of each move's region before its first move (read where
            ``first``), or a 0-d int64 tensor for every region.
        emitted: events the call already emitted (see :func:`crossings`).

    Returns:
        ``(crossings, q)``: the crossings, ``move`` indexing the given moves, and the
        ``(S,)`` int64 reference index after each move (:func:`reference_index`).

    Example:
        >>> floor_u = torch.tensor([1, 3, -1])
        >>> first = torch.tensor([True, False, True])
        >>> cross, q = rule_crossings(floor_u, floor_u == 9, first, torch.tensor([0, 0, 1]))
        >>> cross.move.tolist(), cross.level.tolist(), q.tolist()
        ([0, 1, 1, 2], [1, 2, 3, 0], [1, 3, 0])
    """
    q = reference_index(floor_u, on_level, first, q_start)
    q_before = torch.empty_like(q)
    q_before[1:] = q[:-1]
    q_before = torch.where(first, q_start, q_before)
    return crossings(q_before, q, emitted=emitted), q
