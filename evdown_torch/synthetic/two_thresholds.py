"""The DVS reference rule with different ON and OFF thresholds: a real pixel's comparators.

The synthetic pixel model (:mod:`evdown_torch.synthetic.pixel_model`) is its one user; the
single-threshold rule the downscalers use is :mod:`~evdown_torch.transforms.functional.reference`.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import where_true

__all__ = [
    "PixelSamples",
    "two_threshold_counts",
    "two_threshold_crossings",
    "two_threshold_level",
]

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


class PixelSamples(NamedTuple):
    """Samples of many pixels' levels, each pixel's contiguous and in time order (``(M,)`` each).

    The level is linear between consecutive samples of a pixel; a pixel's first sample is its
    starting point (it emits nothing).

    Attributes:
        value: float64 level at each sample.
        first: bool, the sample is its pixel's first.
        base: float64 reference base of each sample's pixel.
        theta_on: float64 ON threshold (positive) of each sample's pixel.
        theta_off: float64 OFF threshold (positive) of each sample's pixel.
    """

    value: Tensor
    first: Tensor
    base: Tensor
    theta_on: Tensor
    theta_off: Tensor


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
    samples: PixelSamples, a_start: Tensor, b_start: Tensor
) -> tuple[Tensor, Tensor]:
    """ON and OFF counts ``(a, b)`` after each sample, under the two-threshold reference rule.

    At a pixel's first sample ``level(a, b) - theta_off < value < level(a, b) + theta_on``
    must hold. Reaching a level counts, as in the one-threshold rule.

    Args:
        samples: the pixels' samples (:class:`PixelSamples`).
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
        >>> a, b = two_threshold_counts(PixelSamples(v, first, z, on, off), zi, zi)
        >>> a.tolist(), b.tolist()  # ON at 0.2, 0.4; OFF at 0.3, 0.2, ..., -0.2
        ([0, 2, 2, 2], [0, 0, 2, 6])
    """
    value, first, base, theta_on, theta_off = samples
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
    starts = where_true(run_start)
    boundary = run_start | first
    next_boundary = torch.flip(torch.cummin(torch.flip(torch.where(boundary, index, m), [0]),
                                            0).values, [0])
    after = torch.full((m,), m, dtype=torch.int64, device=device)
    after[:-1] = next_boundary[1:]
    run_end = after.index_select(0, starts) - 1
    pixel_of = torch.cumsum(first, 0) - 1
    run_pixel = pixel_of.index_select(0, starts)
    n_pixels = int(pixel_of[-1]) + 1
    first_index = where_true(first)
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
    samples: PixelSamples, a: Tensor, b: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """One entry per event of :func:`two_threshold_counts`' result, in sample then time order.

    Args:
        samples: the pixels' samples (:class:`PixelSamples`).
        a: ``(M,)`` int64 ON count after each sample (:func:`two_threshold_counts`).
        b: ``(M,)`` int64 OFF count after each sample.

    Returns:
        ``(segment, level, on)``: index of the sample that ends the event's segment (int64),
        the float64 level reached (the event happens where the linear segment reaches it) and
        the polarity (bool, True for ON).
    """
    value, first, base, theta_on, theta_off = samples
    da = torch.zeros_like(a)
    db = torch.zeros_like(b)
    torch.sub(a[1:], a[:-1], out=da[1:])
    torch.sub(b[1:], b[:-1], out=db[1:])
    da = torch.where(first, 0, da)
    db = torch.where(first, 0, db)
    count = da + db  # a segment is monotone: one of them is zero
    changed = where_true(count != 0)
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
