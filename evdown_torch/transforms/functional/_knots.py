"""Knots of a pixel and region breakpoints, shared by the linear and cubic estimators.

SEMANTICS.md, methods 4 and 5: each pixel's log-luminance is a curve through its *knots*, one
per distinct time at which the pixel has events, at the level after all its events at that
time (ON +1, OFF -1), plus a front knot ``(t_start, 0)`` when the pixel's first event is later
than ``t_start`` and a back knot ``(t_end, last level)`` when its last knot is earlier than
``t_end``. So every active pixel's curve spans exactly ``[t_start, t_end]``; a pixel without
events stays at level 0 and is not represented.

A region's mean curve ``M_r`` has its breakpoints at the union of its pixels' knot times. This
module builds, without a Python loop over events, pixels or regions:

* the knots of every active pixel in *pixel order* (grouped by region, then by pixel, then in
  time order), and
* the breakpoints of every active region (grouped by region, in time order; the first is at
  ``t_start``, the last at ``t_end``), with the breakpoint index of every knot.

It also holds the small pieces both estimators share to turn a region's level into events:
the exact level test (:func:`level_index`) and the output assembly (:func:`emit`).
"""

from __future__ import annotations

from fractions import Fraction
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch.events import Events
from evdown_torch.transforms.functional._common import region_of
from evdown_torch.transforms.functional._reference import group_by_region

#: A region level within this many thresholds of a level is on it (see :func:`level_index`).
SNAP = 1e-9


class Knots(NamedTuple):
    """Knots of every active pixel and breakpoints of every active region.

    ``K`` knots in pixel order (regions ascending, pixels ascending inside a region, time
    ascending inside a pixel); ``B`` breakpoints in region order, time ascending inside a
    region.

    Attributes:
        t: ``(K,)`` knot times, the dtype of the events' ``t``.
        level: ``(K,)`` int64 pixel level at the knot (events counted ON +1, OFF -1).
        first: ``(K,)`` bool, the knot is its pixel's first (always at ``t_start``).
        last: ``(K,)`` bool, the knot is its pixel's last (always at ``t_end``).
        breakpoint: ``(K,)`` int64 index of the region breakpoint at the knot's time.
        bp_t: ``(B,)`` breakpoint times, the dtype of the events' ``t``.
        bp_region: ``(B,)`` int64 region id ``ry * Wo + rx``.
        bp_first: ``(B,)`` bool, the region's first breakpoint (at ``t_start``).
        bp_last: ``(B,)`` bool, the region's last breakpoint (at ``t_end``).
    """

    t: Tensor
    level: Tensor
    first: Tensor
    last: Tensor
    breakpoint: Tensor
    bp_t: Tensor
    bp_region: Tensor
    bp_first: Tensor
    bp_last: Tensor


def changes(values: Tensor) -> Tensor:
    """``(N,)`` bool: True where ``values`` differs from its predecessor (True at 0)."""
    flags = torch.ones(values.shape[0], dtype=torch.bool, device=values.device)
    torch.ne(values[1:], values[:-1], out=flags[1:])
    return flags


def ends(starts: Tensor) -> Tensor:
    """``(N,)`` bool: True at the last element of each run, given the runs' ``starts``."""
    flags = torch.ones_like(starts)
    flags[:-1] = starts[1:]
    return flags


def run_index(starts: Tensor) -> Tensor:
    """``(N,)`` int64 index of the run each element belongs to, given the runs' ``starts``."""
    return torch.cumsum(starts, 0) - 1


def repeat_index(counts: Tensor) -> Tensor:
    """``repeat_interleave(arange(len(counts)), counts)``, faster on the CPU.

    Args:
        counts: ``(M,)`` non-negative int64.

    Returns:
        ``(counts.sum(),)`` int64, index ``i`` repeated ``counts[i]`` times.
    """
    total = int(counts.sum())
    marks = torch.zeros(total + 1, dtype=torch.int64, device=counts.device)
    starts = torch.cumsum(counts, 0) - counts
    marks.index_add_(0, starts, torch.ones_like(counts))
    return torch.cumsum(marks[:total], 0) - 1


def pixel_knots(events: Events, *, factor: tuple[int, int], out_width: int) -> Knots:
    """Knots of every active pixel and breakpoints of every active region.

    Args:
        events: ``N >= 1`` events in stable time order.
        factor: ``(fx, fy)``.
        out_width: ``Wo``, the output sensor width.

    Returns:
        The :class:`Knots`.

    Example:
        >>> ev = Events.from_columns([0, 1, 0], [0, 0, 0], [0, 5, 5], [1, 1, 1])
        >>> k = pixel_knots(ev, factor=(2, 1), out_width=1)
        >>> k.t.tolist(), k.level.tolist(), k.breakpoint.tolist(), k.bp_t.tolist()
        ([0, 5, 0, 5], [1, 2, 0, 1], [0, 1, 0, 1], [0, 5])
    """
    device = events.device
    fx, fy = factor
    n = events.num_events
    t_start, t_end = events.t[0], events.t[n - 1]

    # Region-time order (stable by region), then pixel order (stable by pixel inside regions).
    rx, ry = region_of(events, factor)
    groups = group_by_region(rx, ry, out_width)
    local = (events.y % fy) * fx + events.x % fx
    key = groups.region * (fx * fy) + local[groups.order]
    to_region_time = torch.sort(key, stable=True).indices  # pixel position -> region-time
    source = groups.order[to_region_time]
    key_p = key[to_region_time]
    t_p = events.t[source]
    step_p = events.p[source].to(torch.int64) * 2 - 1
    del local, key, source

    # Level after every event; the last event of each (pixel, t) run is an event knot.
    new_pixel = changes(key_p)
    level = torch.cumsum(step_p, 0)
    level -= (level - step_p)[new_pixel][run_index(new_pixel)]
    is_knot = ends(new_pixel | changes(t_p))
    kidx = torch.nonzero(is_knot).squeeze(1)
    ek_t, ek_level, ek_key = t_p[kidx], level[kidx], key_p[kidx]
    del new_pixel, level, is_knot, t_p, step_p, key_p
    ke = kidx.shape[0]
    ek_first = changes(ek_key)
    ek_last = ends(ek_first)
    front = ek_first & (ek_t > t_start)
    back = ek_last & (ek_t < t_end)

    # The full knot list in pixel order: front knot before, back knot after a pixel's knots.
    front_count = torch.cumsum(front, 0)
    back_count = torch.cumsum(back, 0)
    pos = torch.arange(ke, device=device) + front_count + back_count - back.to(torch.int64)
    total = ke + int(front_count[-1]) + int(back_count[-1])
    front_pos, back_pos = pos[front] - 1, pos[back] + 1
    t = torch.empty(total, dtype=events.t.dtype, device=device)
    t[pos] = ek_t
    t[front_pos] = t_start
    t[back_pos] = t_end
    lev = torch.empty(total, dtype=torch.int64, device=device)
    lev[pos] = ek_level
    lev[front_pos] = 0
    lev[back_pos] = ek_level[back]
    first = torch.zeros(total, dtype=torch.bool, device=device)
    first[pos[ek_first & ~front]] = True
    first[front_pos] = True
    last = ends(first)

    # Breakpoints: the distinct (region, t) of the event knots in region-time order, with one
    # candidate at t_start before and one at t_end after each active region's event knots.
    rt_pos = to_region_time[kidx]
    del kidx, to_region_time
    rt_mask = torch.zeros(n, dtype=torch.bool, device=device)
    rt_mask[rt_pos] = True
    rt_ordinal = torch.cumsum(rt_mask, 0) - 1
    ek_ordinal = rt_ordinal[rt_pos]
    rt_knots = torch.nonzero(rt_mask).squeeze(1)
    del rt_mask, rt_ordinal, rt_pos
    ekr_region = groups.region[rt_knots]
    ekr_t = events.t[groups.order[rt_knots]]
    del rt_knots, groups
    region_start = changes(ekr_region)
    region_rank = run_index(region_start)
    n_regions = int(region_rank[-1]) + 1
    cand_pos = torch.arange(ke, device=device) + 2 * region_rank + 1
    start_pos = cand_pos[region_start] - 1
    end_pos = cand_pos[ends(region_start)] + 1
    cand_t = torch.empty(ke + 2 * n_regions, dtype=events.t.dtype, device=device)
    cand_t[cand_pos] = ekr_t
    cand_t[start_pos] = t_start
    cand_t[end_pos] = t_end
    cand_region = torch.empty(ke + 2 * n_regions, dtype=torch.int64, device=device)
    cand_region[cand_pos] = ekr_region
    cand_region[start_pos] = ekr_region[region_start]
    cand_region[end_pos] = ekr_region[region_start]
    new_bp = changes(cand_region) | changes(cand_t)
    bp_of_cand = run_index(new_bp)
    bp_t, bp_region = cand_t[new_bp], cand_region[new_bp]
    bp_first = changes(bp_region)

    # Breakpoint of every knot: event knots by position, front/back at the region's ends.
    breakpoint = torch.empty(total, dtype=torch.int64, device=device)
    breakpoint[pos] = bp_of_cand[cand_pos[ek_ordinal]]
    rank_of_region = torch.empty(int(ekr_region[-1]) + 1, dtype=torch.int64, device=device)
    rank_of_region[ekr_region[region_start]] = torch.arange(n_regions, device=device)
    key_region = torch.div(ek_key, fx * fy, rounding_mode="floor")
    breakpoint[front_pos] = bp_of_cand[start_pos[rank_of_region[key_region[front]]]]
    breakpoint[back_pos] = bp_of_cand[end_pos[rank_of_region[key_region[back]]]]
    return Knots(t, lev, first, last, breakpoint, bp_t, bp_region, bp_first, ends(bp_first))


def level_index(
    whole: Tensor, part: Tensor, pixels: Tensor, threshold: Fraction
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
        pixels: int64 ``n_r``.
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
    numerator = whole * b
    denominator = pixels * a
    exact_floor = torch.div(numerator, denominator, rounding_mode="floor")
    exact_on = exact_floor * denominator == numerator
    u = (whole.to(torch.float64) + part) * b / denominator.to(torch.float64)
    nearest = torch.round(u)
    snapped = (u - nearest).abs() <= SNAP
    float_floor = torch.where(snapped, nearest, torch.floor(u)).to(torch.int64)
    exact = part == 0
    floor_u = torch.where(exact, exact_floor, float_floor)
    on_level = torch.where(exact, exact_on, snapped)
    return floor_u, on_level


def level_value(level: Tensor, pixels: Tensor, threshold: Fraction) -> Tensor:
    """``n_r * theta * j`` as float64, the value of ``n_r * M_r`` on level ``j``."""
    a, b = threshold.numerator, threshold.denominator
    return (level * pixels * a).to(torch.float64) / b


def level_changes(knots: Knots) -> Tensor:
    """``(K,)`` int64 change of its pixel's level at each knot (the level itself at the first)."""
    change = knots.level.clone()
    change[1:] -= knots.level[:-1]
    change[knots.first] = knots.level[knots.first]
    return change


def segmented_cumsum(values: Tensor, starts: Tensor) -> Tensor:
    """Cumulative sum of ``values`` restarting at every ``starts``."""
    total = torch.cumsum(values, 0)
    return total - (total - values)[starts][run_index(starts)]


def piece_time(t0: Tensor, t1: Tensor, s: Tensor) -> Tensor:
    """Time at normalised position ``s`` in ``[0, 1]`` of the pieces ``[t0, t1]``.

    Integer times are rounded half up, ``t0 + floor(s * (t1 - t0) + 0.5)``, computed from the
    piece's start so that shifting the clock shifts the result exactly. ``s == 1`` gives
    ``t1`` exactly.
    """
    span = t1 - t0
    if t0.is_floating_point():
        return torch.where(s >= 1, t1, torch.minimum(t0 + s * span, t1))
    return t0 + torch.floor(s * span.to(torch.float64) + 0.5).to(torch.int64)


def emit(region: Tensor, t: Tensor, on: Tensor, out_width: int) -> Events:
    """Output events of regions ``region`` at times ``t``, sorted by ``t`` (stable)."""
    t, order = torch.sort(t, stable=True)
    region = region[order]
    return Events(
        region % out_width, torch.div(region, out_width, rounding_mode="floor"), t, on[order]
    )
