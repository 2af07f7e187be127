"""LinearEstimation's compiled region solver: the polylines' sums and the crossings' place.

One region at a time, what :func:`~..estimation.linear.linear_regions` computes over a chunk
of regions, with the same floats in the same order (:func:`linear_sums`): each slope as
``rise / run``; the region's fixed-point scale from its steepest slope; the slope sums'
high parts in int64 and low parts added at each breakpoint in pixel order (as
``index_add_`` adds them), then summed along the breakpoints from 0.0 (as ``cumsum`` does);
the pixels' progress as the running sum of ``slope_sum * gap - whole_change``, restarted
where every pixel has a knot. :func:`linear_position` places a crossing on its piece by
linear interpolation, as the eager solver does. Neither path fuses a multiply and an add.
"""

from __future__ import annotations

import math

import numpy as np

from evdown_torch.transforms.functional.compiled._numba import compiled_loop

__all__ = ["linear_position", "linear_sums"]


@compiled_loop
def linear_sums(
    k_t: np.ndarray, k_level: np.ndarray, k_bp: np.ndarray, k_first: np.ndarray, nk: int,
    bp_t: np.ndarray, nbp: int, per_region: int, slope: np.ndarray, high_bp: np.ndarray,
    low_bp: np.ndarray, count_bp: np.ndarray, whole: np.ndarray, part: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """One region's ``n_r * M_r`` at its breakpoints: the exact ``whole`` and the ``part``.

    As :func:`~..estimation.linear.linear_regions` computes them: each knot's slope to the
    next (0 at a pixel's last), the region's fixed-point scale from its steepest slope, the
    slope sum's changes per breakpoint (high parts in int64, low parts added in pixel order),
    then along the breakpoints the slope sum, the integer levels and the pixels' progress,
    restarted where every pixel has a knot.
    """
    steepest = 0.0
    for k in range(nk):
        if k + 1 < nk and not k_first[k + 1]:
            slope[k] = float(k_level[k + 1] - k_level[k]) / float(k_t[k + 1] - k_t[k])
        else:
            slope[k] = 0.0
        steepest = max(steepest, abs(slope[k]))
    scale = 1.0
    if steepest != 0.0:
        scale = math.ldexp(1.0, 60 - math.frexp(steepest * per_region)[1])
    high_bp[:nbp] = 0
    low_bp[:nbp] = 0.0
    count_bp[:nbp] = 0
    whole[:nbp] = 0
    high_previous, low_previous, level_previous = 0, 0.0, 0
    for k in range(nk):
        high_f = np.rint(slope[k] * scale)
        low = slope[k] - high_f / scale
        high = np.int64(high_f)
        i = np.uint64(k_bp[k])  # (``_numba``, "Unsigned indices")
        if k_first[k]:
            high_previous, low_previous, level_previous = 0, 0.0, 0
            high_bp[i] += high
            low_bp[i] += low
        else:
            high_bp[i] += high - high_previous
            low_bp[i] += low - low_previous
        whole[i] += k_level[k] - level_previous
        count_bp[i] += 1
        high_previous, low_previous, level_previous = high, low, k_level[k]
    high_sum, low_sum, slope_sum, running, idle_total = 0, 0.0, 0.0, 0.0, 0.0
    for i in range(nbp):
        high_sum += high_bp[i]
        low_sum += low_bp[i]
        step = 0.0
        if i:
            whole[i] += whole[i - 1]
            step = slope_sum * float(bp_t[i] - bp_t[i - 1]) - float(whole[i] - whole[i - 1])
        slope_sum = float(high_sum) / scale + low_sum
        running += step
        if count_bp[i] == count_bp[0]:
            idle_total = running
        part[i] = running - idle_total


@compiled_loop
def linear_position(target: float, whole_begin: int, part_begin: float, whole_end: int,
                    part_end: float) -> float:  # pragma: no cover - compiled
    """Where ``n_r * M_r`` reaches ``target`` on a linear piece, in ``[0, 1]`` (NaN: 0)."""
    rise = float(whole_end - whole_begin)
    s = ((target - float(whole_begin)) - part_begin) / (rise + (part_end - part_begin))
    return 0.0 if np.isnan(s) else min(max(s, 0.0), 1.0)
