"""The DVS reference rule and region grouping, shared by the log-luminance kernels.

A downscaled pixel watches a level ``M(t)`` with contrast threshold ``theta`` and keeps a
reference index ``q``: it emits ON and increments ``q`` whenever ``M`` reaches
``theta * (q + 1)``, OFF and decrements whenever ``M`` reaches ``theta * (q - 1)``.

The kernels sample ``M`` at the end of monotone *steps* (one input event for EventCount, one
monotone piece of the interpolated curve for the linear and cubic methods). Write
``u = M / theta`` at the end of a step. After the step, ``q`` always lies in
``[floor(u), ceil(u)]``:

* on a level (``u`` an integer), ``q = u``;
* strictly inside a cell ``(m, m + 1)``, ``q`` is ``m + 1`` if the walk entered the cell from
  above and ``m`` if it entered from below, and it keeps that value while it stays in the cell.

So ``q`` after every step follows from each step's ``(floor(u), u is an integer)`` and its
predecessor's, with a forward fill over runs of steps in one cell: no sequential scan. This is
the clamp recurrence ``q_k = clamp(q_{k-1}, floor(u_k), ceil(u_k))`` solved in closed form.

This module is the rule's one home: the exact level test (:func:`level_index`), the value of a
level (:func:`level_value`), the reference index (:func:`reference_index`) and its crossings
(:func:`crossings`, :func:`step_crossings`), used by the kernels and the synthetic pixel model.
"""

from __future__ import annotations

from fractions import Fraction
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import changes, stable_sort_small, take, where_true
from evdown_torch.checks import check_output_count

__all__ = [
    "MAX_DENOMINATOR",
    "SNAP",
    "Crossings",
    "RegionGroups",
    "capped_threshold",
    "crossings",
    "group_by_region",
    "level_index",
    "level_value",
    "reference_index",
    "step_crossings",
    "threshold_fraction",
    "two_threshold_counts",
    "two_threshold_crossings",
    "two_threshold_level",
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
    """Reference index ``q`` after each step, for steps grouped by region in time order.

    Args:
        floor_u: ``(N,)`` int64 ``floor(M / theta)`` at the end of each step.
        on_level: ``(N,)`` bool, ``M / theta`` is an integer at the end of the step.
        first: ``(N,)`` bool, the step is the first of its region.
        q_start: ``(N,)`` int64, the region's ``q`` before its first step (read where
            ``first``), or a 0-d int64 tensor for all regions (0 for fresh pixels).

    Returns:
        ``(N,)`` int64 reference index after each step.

    Example:
        >>> import torch
        >>> u = torch.tensor([0.5, 1.0, 0.5, -0.5, 0.5])  # M / theta after each step
        >>> fl = torch.floor(u).long()
        >>> first = torch.tensor([True, False, False, False, False])
        >>> reference_index(fl, u == fl, first, torch.tensor(0)).tolist()
        [0, 1, 1, 0, 0]
    """
    if floor_u.shape[0] == 0:
        return floor_u.clone()
    prev_floor = floor_u.roll(1)
    # A run of steps sharing one value starts at a region's first step, on a level, right
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
    """Level crossings of all steps, in step order and, inside a step, in time order.

    Attributes:
        step: ``(K,)`` int64 index of the step that crossed the level.
        level: ``(K,)`` int64 level index ``j`` crossed (the level is ``theta * j``).
        on: ``(K,)`` bool, ON (upward) crossing.
    """

    step: Tensor
    level: Tensor
    on: Tensor


def crossings(q_before: Tensor, q_after: Tensor, *, emitted: int = 0) -> Crossings:
    """Expand each step's change of reference index into one crossing per level.

    A step taking ``q`` from ``a`` to ``b > a`` crosses levels ``a + 1, ..., b`` upward (ON);
    from ``a`` to ``b < a`` it crosses ``a - 1, ..., b`` downward (OFF).

    Args:
        q_before: ``(N,)`` int64 index before each step.
        q_after: ``(N,)`` int64 index after each step.
        emitted: events the call already emitted (earlier chunks of the stream).

    Returns:
        The :class:`Crossings`, ``K = sum |q_after - q_before|``.

    Raises:
        ValueError: when ``emitted + K`` exceeds
            :func:`~evdown_torch.checks.max_output_events` (counted before building them).

    Example:
        >>> import torch
        >>> c = crossings(torch.tensor([0, 2, 2]), torch.tensor([2, 2, 1]))
        >>> c.step.tolist(), c.level.tolist(), c.on.tolist()
        ([0, 0, 2], [1, 2, 1], [True, True, False])
    """
    delta = q_after - q_before
    changed = where_true(delta != 0)
    delta = take(delta, changed)
    count = delta.abs()
    check_output_count(emitted + int(count.sum()))
    pick = torch.repeat_interleave(torch.arange(changed.shape[0], device=delta.device), count)
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


def step_crossings(
    floor_u: Tensor, on_level: Tensor, first: Tensor, *, emitted: int = 0,
    q_start: Tensor | None = None, q_first: Tensor | None = None, lands_on_levels: bool = False,
) -> Crossings:
    """The reference rule over monotone steps grouped by region, from ``q = q_start``.

    Applies :func:`~evdown_torch.transforms.functional.reference.reference_index` and
    :func:`~evdown_torch.transforms.functional.reference.crossings` to the steps that can
    change ``q`` only: a step that stays strictly inside the cell its predecessor ended in
    keeps ``q`` and crosses nothing, so dropping it changes no other step's result.

    Args:
        floor_u: ``(S,)`` int64 ``floor(M / theta)`` at the end of each step.
        on_level: ``(S,)`` bool, the step ends on a level.
        first: ``(S,)`` bool, the step is its region's first.
        emitted: events the call already emitted (see :func:`crossings`).
        q_start: ``(S,)`` int64 ``q`` of each step's region before its first step (read
            where ``first``; a resumed stream), or ``None`` for 0 (a fresh one).
        q_first: the same values given once per region instead: ``(F,)`` int64, one for
            each True of ``first`` in order (``q_start`` must then be ``None``).
        lands_on_levels: every step ends on each level it reaches (EventCount with an integer
            threshold: a step moves ``b * S`` by one, the levels are multiples of the integer
            ``a * n_r``). A step that ends off every level then keeps ``q``, so only first
            steps and steps on a level are solved.

    Returns:
        The crossings, with ``step`` indexing the given steps.
    """
    if lands_on_levels:
        moved = first | on_level
    else:
        moved = first | on_level | changes(floor_u)
        moved[1:] |= on_level[:-1]
    kept = where_true(moved)
    floor_k, first_k = take(floor_u, kept), take(first, kept)
    if q_start is not None:
        q0 = take(q_start, kept)
    else:
        q0 = torch.zeros_like(floor_k)
        if q_first is not None:  # every first step is kept, in order
            q0[first_k] = q_first.to(q0.dtype)
    q = reference_index(floor_k, take(on_level, kept), first_k, q0)
    q_before = torch.empty_like(q)
    q_before[1:] = q[:-1]
    q_before = torch.where(first_k, q0, q_before)
    cross = crossings(q_before, q, emitted=emitted)
    return Crossings(take(kept, cross.step), cross.level, cross.on)


# --- The reference rule with separate ON and OFF thresholds ---------------------------------
#
# A real DVS pixel has two comparators: ON fires when the level rises ``theta_on`` above the
# reference, OFF when it falls ``theta_off`` below it, and each event moves the reference by
# the threshold it crossed. With ``theta_on != theta_off`` the reachable references no longer
# form one lattice (each reversal shifts its phase), so the closed form above does not carry
# over: the state after a reversal depends on the whole history. What stays closed-form is a
# monotone *run* of samples: from reference ``r`` a rising run ending at ``E`` emits the ON
# events ``r + k * theta_on <= E``, a falling one the OFF events ``r - k * theta_off >= E``. So
# the rule is a scan over runs (not samples), vectorised across pixels: iteration ``i`` advances
# the ``i``-th run of every pixel that has one. Its cost is (largest number of runs of one
# pixel) small steps plus work linear in the samples; ``docs/benchmarks.md`` measures it in the
# synthetic generator, the one user.
#
# The reference is kept as two integer counts ``(a, b)`` (ON and OFF events so far): its level
# is ``base + a * theta_on - b * theta_off``, always evaluated by :func:`two_threshold_level`,
# so the comparisons are the same whichever order they are made in.


def two_threshold_level(base: Tensor, a: Tensor, b: Tensor, theta_on: Tensor,
                        theta_off: Tensor) -> Tensor:
    """Reference level ``base + a * theta_on - b * theta_off`` (float64; counts int64)."""
    return base + a.to(base.dtype) * theta_on - b.to(base.dtype) * theta_off


#: Margin (in thresholds) taken off the float estimate of the levels crossed, so that the
#: estimate can only fall short, by at most one; one exact comparison then settles it.
_ESTIMATE_MARGIN = 1e-9


def _crossed(value: Tensor, base: Tensor, a: Tensor, b: Tensor, theta_on: Tensor,
             theta_off: Tensor, up: Tensor, sign: Tensor, inv_theta: Tensor) -> Tensor:
    """Levels reached by moving monotonically from the reference ``(a, b)`` to ``value``.

    Rising (``up`` 1.0, ``sign`` 1.0, ``inv_theta = 1 / theta_on``): the largest ``k >= 0``
    with ``level(a + k, b) <= value``; falling (``up`` 0.0, ``sign`` -1.0,
    ``inv_theta = 1 / theta_off``): the largest ``k >= 0`` with ``level(a, b + k) >= value``.
    Counts ``a``, ``b`` and the result are float64 holding integers (exact below 2**53).
    """
    ref = base + a * theta_on - b * theta_off  # two_threshold_level, in float counts
    k = ((value - ref) * sign * inv_theta - _ESTIMATE_MARGIN).floor_().clamp_min_(0)
    k1 = k + 1
    down = 1 - up
    level = base + (a + up * k1) * theta_on - (b + down * k1) * theta_off
    return k.add_((level - value) * sign <= 0)


def _direction_terms(rising: Tensor, theta_on: Tensor, theta_off: Tensor
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """``(up, sign, inv_theta)`` of :func:`_crossed` for a direction (True: rising)."""
    up = rising.to(theta_on.dtype)
    return up, up * 2 - 1, 1 / torch.where(rising, theta_on, theta_off)


def two_threshold_counts(
    value: Tensor,
    first: Tensor,
    base: Tensor,
    theta_on: Tensor,
    theta_off: Tensor,
    a_start: Tensor,
    b_start: Tensor,
) -> tuple[Tensor, Tensor]:
    """ON and OFF counts ``(a, b)`` after each sample, under the two-threshold reference rule.

    Samples of one pixel are contiguous and in time order; the level is linear between
    consecutive samples of a pixel. A pixel's first sample is its starting point (it emits
    nothing; there ``level(a, b) - theta_off < value < level(a, b) + theta_on`` must hold).
    Reaching a level counts, as in the one-threshold rule.

    Args:
        value: ``(M,)`` float64 level at each sample.
        first: ``(M,)`` bool, the sample is its pixel's first.
        base: ``(M,)`` float64 reference base of each sample's pixel.
        theta_on: ``(M,)`` float64 ON threshold (positive) of each sample's pixel.
        theta_off: ``(M,)`` float64 OFF threshold (positive) of each sample's pixel.
        a_start: ``(M,)`` int64 ON count at each pixel's first sample (read where ``first``).
        b_start: ``(M,)`` int64 OFF count there.

    Returns:
        ``(a, b)``: ``(M,)`` int64 ON and OFF counts after each sample.

    Example:
        >>> import torch
        >>> v = torch.tensor([0.0, 0.5, 0.2, -0.25], dtype=torch.float64)
        >>> first = torch.tensor([True, False, False, False])
        >>> z = torch.zeros(4, dtype=torch.float64)
        >>> on, off = torch.full_like(v, 0.2), torch.full_like(v, 0.1)
        >>> zi = torch.zeros(4, dtype=torch.int64)
        >>> a, b = two_threshold_counts(v, first, z, on, off, zi, zi)
        >>> a.tolist(), b.tolist()  # ON at 0.2, 0.4; OFF at 0.3, 0.2, ..., -0.2
        ([0, 2, 2, 2], [0, 0, 2, 6])
    """
    m = value.shape[0]
    device = value.device
    if m == 0:
        return a_start.clone(), b_start.clone()
    index = torch.arange(m, device=device)
    diff = torch.zeros(m, dtype=value.dtype, device=device)
    torch.sub(value[1:], value[:-1], out=diff[1:])
    direction = torch.sign(diff).to(torch.int8)
    direction[first] = 0
    moving = direction != 0
    # direction of the pixel's previous moving segment (0 before its first)
    last_moving = torch.cummax(torch.where(moving | first, index, -1), 0).values
    previous = torch.zeros(m, dtype=torch.int8, device=device)
    previous[1:] = direction.index_select(0, last_moving[:-1].clamp_min(0))
    previous[1:] = torch.where(first[1:], 0, previous[1:])
    run_start = moving & (direction != previous)
    # a run ends at the pixel's last sample before the next run start (or the pixel's end)
    starts = run_start.nonzero().squeeze(1)
    boundary = run_start | first
    next_boundary = torch.flip(torch.cummin(torch.flip(torch.where(boundary, index, m), [0]),
                                            0).values, [0])
    after = torch.full((m,), m, dtype=torch.int64, device=device)
    after[:-1] = next_boundary[1:]
    run_end = after.index_select(0, starts) - 1
    pixel_of = torch.cumsum(first, 0) - 1
    run_pixel = pixel_of.index_select(0, starts)
    n_pixels = int(pixel_of[-1]) + 1
    first_index = first.nonzero().squeeze(1)
    a_state = a_start.index_select(0, first_index).clone()
    b_state = b_start.index_select(0, first_index).clone()
    n_runs = starts.shape[0]
    run_a0 = torch.empty(n_runs, dtype=torch.int64, device=device)
    run_b0 = torch.empty(n_runs, dtype=torch.int64, device=device)
    if n_runs:
        # runs in iteration-major order: pixels by decreasing run count, so that iteration i
        # touches a prefix of them
        per_pixel = torch.bincount(run_pixel, minlength=n_pixels)
        by_count = torch.sort(per_pixel, descending=True, stable=True).indices
        rank = torch.empty_like(by_count)
        rank[by_count] = torch.arange(n_pixels, device=device)
        first_run = torch.cumsum(per_pixel, 0) - per_pixel
        within = torch.arange(n_runs, device=device) - first_run.index_select(0, run_pixel)
        order = torch.sort(within * n_pixels + rank.index_select(0, run_pixel)).indices
        active = torch.bincount(within, minlength=int(per_pixel.max())).tolist()
        end = run_end.index_select(0, order)
        end_value = value.index_select(0, end)
        rising = direction.index_select(0, starts.index_select(0, order)) > 0  # per run
        pix = by_count
        at = first_index.index_select(0, pix)
        base_p, on_p, off_p = (c.index_select(0, at) for c in (base, theta_on, theta_off))
        a_p = a_state.index_select(0, pix).to(value.dtype)  # float counts: exact integers
        b_p = b_state.index_select(0, pix).to(value.dtype)
        start_it = starts.index_select(0, order)
        up_it, sign_it, inv_it = _direction_terms(rising, theta_on.index_select(0, start_it),
                                                  theta_off.index_select(0, start_it))
        down_it = 1 - up_it
        a0_it = torch.empty(n_runs, dtype=value.dtype, device=device)
        b0_it = torch.empty(n_runs, dtype=value.dtype, device=device)
        offset = 0
        for n in active:  # the scan: iteration i advances the i-th run of each pixel
            sl = slice(offset, offset + n)
            offset += n
            a_n, b_n = a_p[:n], b_p[:n]
            a0_it[sl] = a_n
            b0_it[sl] = b_n
            k = _crossed(end_value[sl], base_p[:n], a_n, b_n, on_p[:n], off_p[:n], up_it[sl],
                         sign_it[sl], inv_it[sl])
            a_n.addcmul_(up_it[sl], k)  # in place: a_p, b_p hold the state
            b_n.addcmul_(down_it[sl], k)
        run_a0[order] = a0_it.to(torch.int64)
        run_b0[order] = b0_it.to(torch.int64)
    # every sample: the counts at its run's start, plus the levels crossed up to its value
    run_of = torch.cumsum(run_start, 0) - 1
    in_run = (run_of >= 0) & ~first
    if n_runs:
        r = run_of.clamp_min(0)
        in_run &= pixel_of == run_pixel.index_select(0, r)
        a0 = torch.where(in_run, run_a0.index_select(0, r), 0)
        b0 = torch.where(in_run, run_b0.index_select(0, r), 0)
        up = direction.index_select(0, starts.index_select(0, r)) > 0
    else:
        a0 = b0 = torch.zeros(m, dtype=torch.int64, device=device)
        up = torch.ones(m, dtype=torch.bool, device=device)
    # samples before a pixel's first run (flat start) keep the starting counts
    pixel_first = first_index.index_select(0, pixel_of)
    a0 = torch.where(in_run, a0, a_start.index_select(0, pixel_first))
    b0 = torch.where(in_run, b0, b_start.index_select(0, pixel_first))
    up_f, sign, inv_theta = _direction_terms(up, theta_on, theta_off)
    k = _crossed(value, base, a0.to(value.dtype), b0.to(value.dtype), theta_on, theta_off,
                 up_f, sign, inv_theta).to(torch.int64)
    k = torch.where(in_run, k, 0)
    return a0 + k * up, b0 + k * ~up


def two_threshold_crossings(
    value: Tensor,
    first: Tensor,
    base: Tensor,
    theta_on: Tensor,
    theta_off: Tensor,
    a: Tensor,
    b: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """One entry per event of :func:`two_threshold_counts`' result, in sample then time order.

    Args:
        value, first, base, theta_on, theta_off: as for :func:`two_threshold_counts`.
        a, b: ``(M,)`` int64 counts after each sample (its result).

    Returns:
        ``(segment, level, on)``: index of the sample that ends the event's segment (int64),
        the float64 level reached (the event happens where the linear segment reaches it) and
        the polarity (bool, True for ON).
    """
    da = torch.zeros_like(a)
    db = torch.zeros_like(b)
    torch.sub(a[1:], a[:-1], out=da[1:])
    torch.sub(b[1:], b[:-1], out=db[1:])
    da = torch.where(first, 0, da)
    db = torch.where(first, 0, db)
    count = da + db  # a segment is monotone: one of them is zero
    changed = count.nonzero().squeeze(1)
    count = count.index_select(0, changed)
    segment = torch.repeat_interleave(changed, count)
    offsets = torch.cumsum(count, 0) - count
    within = torch.arange(segment.shape[0], device=value.device)
    within -= torch.repeat_interleave(offsets, count)
    on = da.index_select(0, segment) > 0
    prev = segment - 1
    a_prev, b_prev = a.index_select(0, prev), b.index_select(0, prev)
    step = within + 1
    level = two_threshold_level(base.index_select(0, segment),
                                torch.where(on, a_prev + step, a_prev),
                                torch.where(on, b_prev, b_prev + step),
                                theta_on.index_select(0, segment),
                                theta_off.index_select(0, segment))
    return segment, level, on
