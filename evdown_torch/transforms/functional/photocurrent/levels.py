"""What both modes of photocurrent pooling share (docs/semantics.md, method 7).

The range checks of the contrast, threshold and levels, the geometry of a region's pixels,
the exact pixel levels after each event, a region's log-mean-exp of its levels, and the
level snap of ``u = log(I_r) / theta`` (a ``u`` within :data:`~.reference.SNAP` of an integer
is on it). The modes themselves: :mod:`.events_mode` and :mod:`.frames_mode`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._regions import pixel_columns, region_xy
from evdown_torch._tensors import (
    changes,
    continued_cumsum,
    last_of_runs,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.events import Events, polarity_sign
from evdown_torch.transforms.functional.reference import SNAP

__all__ = ["EXP_TABLE_LEVELS", "PixelLevels", "check_contrast_range", "check_level_range",
           "log_mean_exp", "pixel_levels", "region_levels_after", "region_pixel_ids", "snap"]


def check_contrast_range(contrast: float, threshold: float) -> None:
    """Refuse contrasts whose results float64 cannot represent (see the transform)."""
    if not 1e-6 <= contrast <= 50.0:
        raise ValueError(
            f"contrast must lie in [1e-6, 50] (log units per input event), got {contrast!r}"
        )
    if not 1e-6 <= threshold <= 1e6:
        raise ValueError(f"threshold must lie in [1e-6, 1e6] (log units), got {threshold!r}")


def check_level_range(max_level: int, contrast: float, threshold: float) -> None:
    """Refuse streams whose level index ``c * L / theta`` would lose integer precision."""
    if max_level * contrast / threshold >= 2.0**50:
        raise ValueError(
            f"contrast / threshold = {contrast / threshold:g} times up to {max_level} levels "
            "exceeds 2**50 output levels; float64 cannot resolve them"
        )


def snap(u: Tensor) -> tuple[Tensor, Tensor]:
    """``(floor(u), u is on a level)``, a ``u`` within :data:`SNAP` of an integer on it."""
    nearest = torch.round(u)
    offset = u - nearest
    on_level = offset.abs() <= SNAP
    # Below the nearest integer by more than SNAP (|offset| <= 1/2): floor(u) = nearest - 1.
    return nearest.sub_(offset.lt_(-SNAP)).to(torch.int64), on_level


def region_pixel_ids(
    regions: Tensor, sensor_size: tuple[int, int, int], factor: tuple[int, int]
) -> tuple[Tensor, Tensor | None]:
    """Pixel ids ``y * W + x`` of every pixel of ``regions``, and which are inside the sensor.

    ``(R, fx * fy)`` int64 ids and a same-shaped bool mask of those inside the sensor (ids
    outside are 0), ``None`` when the factor divides the sensor (every pixel is inside).
    Regions of stacked recordings (ids past ``Ho * Wo``) are inside where their recording's
    are.
    """
    w, h, _ = sensor_size
    fx, fy = factor
    rows = -(-h // fy) * fy  # the sensor's rows padded to whole regions
    rx, ry = region_xy(regions, -(-w // fx))
    grid = torch.arange(fx * fy, device=regions.device)
    gx, gy = grid % fx, torch.div(grid, fx, rounding_mode="floor")
    if w % fx == 0 and h % fy == 0:
        corner = ry.mul_(fy * w).add_(rx, alpha=fx)
        return corner[:, None] + (gy * w + gx), None
    px = rx[:, None] * fx + gx
    py = ry[:, None] * fy + gy
    inside = (px < w) & (torch.remainder(py, rows) < h)
    return torch.where(inside, py * w + px, 0), inside


#: Most levels below a row's brightest for which :func:`log_mean_exp` looks its intensities
#: up in a table of ``exp(c * j)`` (one exponential per level that occurs, not per entry).
EXP_TABLE_LEVELS = 1 << 16


def log_mean_exp(
    levels: Tensor, inside: Tensor | None, contrast: float
) -> tuple[Tensor, Tensor]:
    """Per row: brightest level ``m`` and ``sum exp(c * (L - m))`` over the ``inside`` entries.

    The intensities are ``exp(float64(L - m) * c)``, looked up in a table of those values for
    the levels that occur (the same values, bit for bit, as computing each entry's).

    Args:
        levels: ``(R, n)`` int64 pixel levels.
        inside: ``(R, n)`` bool, the entry is a sensor pixel (``None``: all are).
        contrast: ``c``.

    Returns:
        ``(m, s)``: ``(R,)`` int64 and ``(R,)`` float64 in ``[1, n]``.

    Example:
        >>> m, s = log_mean_exp(torch.tensor([[3, 3, 1], [0, -2, 5]]), None, math.log(2))
        >>> m.tolist(), [round(v, 12) for v in s.tolist()]
        ([3, 5], [2.25, 1.0390625])
    """
    if inside is None:
        m = levels.amax(1)
        below = levels - m[:, None]
    else:
        m = torch.where(inside, levels, torch.iinfo(torch.int64).min).amax(1)
        below = torch.where(inside, levels - m[:, None], 0)
    if below.numel() == 0:
        return m, torch.zeros(m.shape, dtype=torch.float64, device=m.device)
    # exp(c * j) is 0.0 in float64 below j = -800 / c: such levels count as that one.
    darkest = max(int(below.min()), -math.ceil(800 / contrast))
    if -darkest < EXP_TABLE_LEVELS:
        table = torch.arange(darkest, 1, device=m.device).to(torch.float64).mul_(contrast).exp_()
        intensity = take(table, below.clamp_(min=darkest).sub_(darkest).view(-1)).view_as(below)
    else:
        intensity = below.to(torch.float64).mul_(contrast).exp_()
    if inside is not None:
        intensity.masked_fill_(~inside, 0.0)
    return m, intensity.sum(1)


class PixelLevels(NamedTuple):
    """Levels after each event of a time-ordered piece, in pixel order."""

    pixel: Tensor  # (n,) int64 pixel id, ascending (time order inside a pixel)
    order: Tensor  # (n,) int64 time position of each
    level: Tensor  # (n,) int64 level of the pixel after the event
    change: Tensor  # (n,) int64 the event's level change, +1 (ON) or -1 (OFF)
    new_state: Tensor  # (H * W,) int64 levels after the piece


def pixel_levels(events: Events, width: int, height: int, levels: Tensor) -> PixelLevels:
    """Exact level of its pixel after every event, starting from ``levels``."""
    pixel = events.y * width + events.x
    pixel, order = stable_sort_small(pixel, width * height)
    change = polarity_sign(take(events.p, order), torch.int64)
    new_pixel = changes(pixel)
    starts = where_true(new_pixel)
    n = pixel.shape[0]
    last = last_of_runs(starts, n)  # run ends
    level, final = continued_cumsum(change.clone(), starts, last,
                                    take(levels, take(pixel, starts)))
    new_state = levels.clone()
    new_state.scatter_(0, take(pixel, last), final)
    return PixelLevels(pixel, order, level, change, new_state)


def region_levels_after(
    events: Events, factor: tuple[int, int], segment: Tensor, firsts: Tensor,
    start: Tensor,
) -> Tensor:
    """The levels of its region's pixels after every event, one row per event (exact).

    Args:
        events: ``N`` events grouped by region (time order inside a region).
        factor: ``(fx, fy)``.
        segment: ``(N,)`` int64 rank of each event's region among the ``S`` regions.
        firsts: ``(S,)`` int64 position of each region's first event.
        start: ``(S, fx * fy)`` int64 levels of each region's pixels before the events, in
            the order of :func:`region_pixel_ids`.

    Returns:
        ``(N, fx * fy)`` int64: row ``i`` holds the levels after event ``i`` of the pixels of
        its region, the event's own pixel moved by its +1 (ON) or -1 (OFF).

    Example:
        >>> ev = Events.from_columns([0, 1, 0], [0, 0, 0], [1, 2, 3], [1, 1, 0])
        >>> start = torch.tensor([[5, 0]])
        >>> region_levels_after(ev, (2, 1), torch.zeros(3, dtype=torch.int64),
        ...                     torch.tensor([0]), start).tolist()
        [[6, 0], [6, 1], [5, 1]]
    """
    fx, fy = factor
    n = events.num_events
    slot = pixel_columns(events, factor)
    rows = torch.zeros(n, fx * fy, dtype=torch.int64, device=slot.device)
    rows.scatter_(1, slot[:, None], polarity_sign(events.p, torch.int64)[:, None])
    rows.cumsum_(0)
    # Each region's rows start from its own levels: take back the sums of the regions before.
    before = torch.zeros_like(start)
    before[1:] = rows[firsts[1:] - 1]
    return rows.add_(take(start - before, segment))
