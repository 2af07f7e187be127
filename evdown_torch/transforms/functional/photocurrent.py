"""Photocurrent pooling kernels (SEMANTICS.md method 7): events to video to events.

Each input pixel keeps an integer level ``L_p`` (ON +1, OFF -1) and its log intensity is
``c * L_p``. A region's photocurrent is the mean of its pixels' intensities,
``I_r = (1 / n_r) * sum exp(c * L_p)``, and the output pixel runs the DVS reference rule on
``log I_r`` at contrast ``theta``: with ``u = log(I_r) / theta``, the shared rule of
:mod:`~evdown_torch.transforms.functional._reference` (floor of ``u`` and whether ``u`` is on a
level, a ``u`` within :data:`~evdown_torch.transforms.functional._knots.SNAP` of an integer
counting as on it).

*Events mode* (:func:`photocurrent_events`): ``log I_r`` changes only at input events. Per
region, the photocurrent after each event is a running sum of the changes ``exp(c * L_after) -
exp(c * L_before)``. Levels stay exact int64; the sums are *re-anchored*: at the start of every
piece of the stream each touched region's sum is recomputed from its pixels' integer levels,
relative to the region's brightest pixel (``sum exp(c * (L_p - m_r))`` lies in ``[1, n_r]``,
so nothing overflows), and inside a piece the changes are summed in fixed point (exact int64
high parts, float64 remainders) so that regions do not pollute each other. Where the running
sum's error bound (a few ulps per change) would exceed ``1e-11 * theta`` of the sum, or an
exponent would leave float64's range, the piece is cut there and the rest re-anchored.

*Frames mode*: :mod:`~evdown_torch.transforms.functional.photocurrent_frames`, which shares
the pixel levels, region geometry and level snap defined here.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import (
    CHUNK_EVENTS,
    changes,
    region_of,
    region_pixel_count,
    region_xy,
    run_index,
    segmented_cumsum,
    sort_by_time,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.checks import output_size
from evdown_torch.events import Events
from evdown_torch.transforms.functional._reference import (
    SNAP,
    RegionGroups,
    crossings,
    reference_index,
)

#: Largest exponent ``c * (L - m_r)`` a piece may reach before it is cut: a pixel rising this
#: far above its region's anchor would make the region's running sum span too many orders of
#: magnitude for its early values to keep their precision (exp(709) overflows anyway).
MAX_EXPONENT = 24.0

#: Unit roundoff of float64.
EPS = 2.0**-53


class PhotocurrentState(NamedTuple):
    """State of a photocurrent pooling stream between chunks (events mode).

    Attributes:
        level: ``(H * W,)`` int64 level of every input pixel (ON +1, OFF -1), index ``y * W + x``.
        index: ``(Ho * Wo,)`` int64 reference index ``q`` of every output region.
        last_t: ``()`` tensor, the latest timestamp seen (``None`` before any event).
    """

    level: Tensor
    index: Tensor
    last_t: Tensor | None


def initial_state(
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    device: torch.device | str | None = None,
    recordings: int = 1,
) -> PhotocurrentState:
    """A fresh state: every pixel at level 0 (intensity 1), every region with ``q = 0``.

    With ``recordings > 1``, the state of that many recordings stacked vertically (recording
    ``b``'s pixel ``(x, y)`` at ``(x, y + b * Ho * fy)``, see
    :mod:`evdown_torch.transforms._batch`).
    """
    w, h, _ = sensor_size
    out_w, out_h, _ = output_size(sensor_size, factor)
    rows = h if recordings == 1 else out_h * factor[1] * recordings
    return PhotocurrentState(
        torch.zeros(w * rows, dtype=torch.int64, device=device),
        torch.zeros(out_w * out_h * recordings, dtype=torch.int64, device=device),
        None,
    )


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
    on_level = (u - nearest).abs() <= SNAP
    return torch.where(on_level, nearest, torch.floor(u)).to(torch.int64), on_level


def region_pixels(
    regions: Tensor, sensor_size: tuple[int, int, int], factor: tuple[int, int]
) -> tuple[Tensor, Tensor]:
    """Pixel ids ``y * W + x`` of every pixel of ``regions``: ``(R, fx * fy)`` int64 and a
    same-shaped bool mask of those inside the sensor (ids outside are 0). Regions of stacked
    recordings (ids past ``Ho * Wo``) are inside where their recording's are."""
    w, h, _ = sensor_size
    fx, fy = factor
    rows = -(-h // fy) * fy  # the sensor's rows padded to whole regions
    rx, ry = region_xy(regions, -(-w // fx))
    grid = torch.arange(fx * fy, device=regions.device)
    px = rx[:, None] * fx + grid % fx
    py = ry[:, None] * fy + torch.div(grid, fx, rounding_mode="floor")
    inside = (px < w) & (torch.remainder(py, rows) < h)
    return torch.where(inside, py * w + px, 0), inside


def log_mean_exp(levels: Tensor, inside: Tensor, contrast: float) -> tuple[Tensor, Tensor]:
    """Per row: brightest level ``m`` and ``sum exp(c * (L - m))`` over the ``inside`` entries.

    Args:
        levels: ``(R, n)`` int64 pixel levels.
        inside: ``(R, n)`` bool, the entry is a sensor pixel.
        contrast: ``c``.

    Returns:
        ``(m, s)``: ``(R,)`` int64 and ``(R,)`` float64 in ``[1, n]``.
    """
    lowest = torch.iinfo(torch.int64).min
    m = torch.where(inside, levels, lowest).amax(1)
    below = torch.where(inside, levels - m[:, None], 0).to(torch.float64).mul_(contrast)
    return m, torch.where(inside, torch.exp(below), 0.0).sum(1)


class _SegmentSums(NamedTuple):
    """Running sums of :func:`_segment_sum` and what an error bound needs of them."""

    total: Tensor  # (N,) float64 running sums
    grid: Tensor  # (N,) int64 grid parts of the values
    scale: Tensor  # (N,) or () float64 grid scale of each value's segment


def _segment_sum(values: Tensor, starts_at: Tensor, segment: Tensor) -> _SegmentSums:
    """Running sum of float64 ``values`` restarting at each segment, without cross-talk.

    Each segment is put on its own fixed-point grid (a power of two fitted to its largest
    value): the grid parts add exactly in int64 and only the remainders, below half a grid
    step, are summed in float64, so a segment's sum carries no rounding of other segments,
    however much larger their values are.

    Args:
        values: ``(N,)`` float64.
        starts_at: ``(S,)`` int64 start of each segment, ascending, the first 0.
        segment: ``(N,)`` int64 segment of each element.
    """
    n = values.shape[0]
    largest = torch.zeros(starts_at.shape[0], dtype=torch.float64, device=values.device)
    largest.scatter_reduce_(0, segment, values.abs(), "amax")
    top = float(largest.max())
    if top == 0.0 or float(largest.min()) >= top * 2.0**-24:
        # Segments of similar magnitudes share one grid: the remainders' sum then drifts by
        # at most n * 2**-53 grid steps, 2**-60 of the smallest segment's largest value.
        scale = torch.tensor(math.ldexp(1.0, 61 - n.bit_length() - math.frexp(top)[1]),
                             dtype=torch.float64, device=values.device)
    else:
        exponent = torch.frexp(largest).exponent.to(torch.float64)
        scale = take(torch.exp2((61 - n.bit_length()) - exponent), segment)
    scaled = values * scale
    high_f = torch.round(scaled)
    rest = scaled.sub_(high_f)
    high = high_f.to(torch.int64)
    del high_f
    total = segmented_cumsum(high, starts_at, segment).to(torch.float64)
    total += segmented_cumsum(rest, starts_at, segment)
    return _SegmentSums(total.div_(scale), high, scale)


def _running_magnitude(sums: _SegmentSums, starts_at: Tensor, segment: Tensor) -> Tensor:
    """Running sums of ``|value|`` from the grid parts (exact to a grid step per value)."""
    size = sums.grid.abs().add_(1)
    return segmented_cumsum(size, starts_at, segment).to(torch.float64).div_(sums.scale)


#: Largest table of ``exp(c * j)`` values :func:`_sum_changes` builds instead of calling exp.
TABLE_SIZE = 1 << 16


def _sum_changes(before: Tensor, on: Tensor, contrast: float) -> tuple[Tensor, Tensor | None]:
    """``exp(c * (before + s)) - exp(c * before)`` for int64 ``before`` (level minus anchor)
    and step ``s = +-1``, from a table of ``exp(c * j) * expm1(+-c)`` when the levels span
    little; and where ``c * before`` exceeds :data:`MAX_EXPONENT` (else ``None``)."""
    lowest, highest = int(before.min()), int(before.max())
    too_bright = None
    if highest * contrast > MAX_EXPONENT:
        too_bright = before > MAX_EXPONENT / contrast
        highest = math.floor(MAX_EXPONENT / contrast)
        before = before.clamp(max=highest)
    expm1 = (math.expm1(-contrast), math.expm1(contrast))
    floor = max(lowest, -math.ceil(800 / contrast))  # exp(c * j) is 0 below
    if highest - floor < TABLE_SIZE:
        j = torch.arange(floor, highest + 1, device=before.device, dtype=torch.float64)
        table = torch.exp(j.mul_(contrast))[:, None] * torch.tensor(
            expm1, dtype=torch.float64, device=before.device)
        index = (before.clamp(min=floor) - floor).mul_(2).add_(on.to(torch.int64))
        return take(table.reshape(-1), index), too_bright
    steps = torch.tensor(expm1, dtype=torch.float64, device=before.device)
    change = torch.exp(before.to(torch.float64).mul_(contrast))
    return change.mul_(take(steps, on.to(torch.int64))), too_bright


class PixelLevels(NamedTuple):
    """Levels after each event of a time-ordered piece, in pixel order."""

    pixel: Tensor  # (n,) int64 pixel id, ascending (time order inside a pixel)
    order: Tensor  # (n,) int64 time position of each
    level: Tensor  # (n,) int64 level of the pixel after the event
    step: Tensor  # (n,) int64 the event's step, +1 (ON) or -1 (OFF)
    new_state: Tensor  # (H * W,) int64 levels after the piece


def pixel_levels(events: Events, width: int, height: int, levels: Tensor) -> PixelLevels:
    """Exact level of its pixel after every event, starting from ``levels``."""
    pixel = events.y * width + events.x
    pixel, order = stable_sort_small(pixel, width * height)
    step = take(events.p, order).to(torch.int64).mul_(2).sub_(1)
    new_pixel = changes(pixel)
    starts = where_true(new_pixel)
    n = pixel.shape[0]
    last = torch.cat([starts[1:] - 1, starts.new_tensor([n - 1] if n else [])])  # run ends
    # One cumulative sum whose first step of each pixel also moves from the previous pixel's
    # last level to this pixel's starting level (a telescoping correction).
    plain = torch.cumsum(step, 0)
    first_level = take(levels, take(pixel, starts))
    final = take(plain, last) - take(plain, starts) + take(step, starts) + first_level
    jump = first_level
    jump[1:] -= final[:-1]
    level = step.index_add(0, starts, jump).cumsum_(0)
    new_state = levels.clone()
    new_state.scatter_(0, take(pixel, last), final)
    return PixelLevels(pixel, order, level, step, new_state)


# --------------------------------------------------------------------------------------------
# Events mode


def photocurrent_events(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    contrast: float,
    threshold: float,
    state: PhotocurrentState | None = None,
    recordings: int = 1,
) -> tuple[Events, PhotocurrentState]:
    """Photocurrent pooling, events mode (SEMANTICS.md method 7): causal, streamable.

    After each input event, in stable time order, its region's ``u = log(I_r) / threshold``
    with ``I_r = mean(exp(contrast * L_p))`` is tested with the DVS reference rule; emitted
    events take the triggering event's ``t``.

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        contrast: ``c``, the input camera's contrast threshold in log units, in [1e-6, 50].
        threshold: ``theta``, the output pixel's contrast threshold in log units.
        state: the state returned for the previous chunk of the same stream, or ``None``.
        recordings: ``B``, for a batch of recordings stacked vertically (recording ``b``'s
            pixel ``(x, y)`` given as ``(x, y + b * Ho * fy)``, see
            :mod:`evdown_torch.transforms._batch`). 1 for one stream.

    Returns:
        ``(output events sorted by t, state after the last event)``.

    Example:
        Two ON events in a 2x1 region at contrast ln 2: the photocurrent goes 1 -> 1.5 -> 2,
        so only the second event reaches the level ``ln 2``.

        >>> ev = Events.from_columns([0, 1], [0, 0], [5, 9], [1, 1])
        >>> out, _ = photocurrent_events(ev, sensor_size=(2, 1, 2), factor=(2, 1),
        ...                              contrast=math.log(2), threshold=math.log(2))
        >>> out.t.tolist(), out.p.tolist()
        ([9], [True])
    """
    check_contrast_range(contrast, threshold)
    events = sort_by_time(events)
    if state is None:
        state = initial_state(sensor_size, factor, events.device, recordings)
    n = events.num_events
    if n == 0:
        return Events.empty(events.t.dtype, events.device), state
    check_level_range(int(state.level.abs().max()) + n, contrast, threshold)
    outputs = []
    # Pieces of a few events per pixel: re-anchoring then costs little (at most the sensor's
    # pixels per piece), and a piece that has to be cut wastes little.
    largest = min(max(4 * sensor_size[0] * sensor_size[1], 1 << 16), CHUNK_EVENTS)
    start, size, emitted = 0, largest, 0
    while start < n:
        stop = min(start + size, n)
        piece = Events(*(column[start:stop] for column in events))
        out, state, used = _events_piece(piece, sensor_size, factor, contrast, threshold, state,
                                         emitted)
        outputs.append(out)
        emitted += out.num_events
        # After a cut (the running sums could not hold the rest), re-anchor there and try
        # shorter pieces for a while: a stream that needed one cut soon needs another.
        size = min(size + size // 4, largest) if start + used == stop else max(used, 1024)
        start += used
    return Events(*(torch.cat(columns) for columns in zip(*outputs, strict=True))), state


def _events_piece(
    events: Events,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    contrast: float,
    threshold: float,
    state: PhotocurrentState,
    emitted: int = 0,
) -> tuple[Events, PhotocurrentState, int]:
    """Events mode on one time-sorted piece anchored at ``state``: ``(output, state, used)``.

    ``emitted`` counts the events of earlier pieces, for the output cap of
    :func:`~evdown_torch.checks.check_output_count`. Where the running sums cannot hold the
    whole piece to the required accuracy, only its events before the first that they cannot
    hold are used (``used >= 1`` events, the output and state are theirs); the caller
    re-anchors there.
    """
    w, h, _ = sensor_size
    out_w = output_size(sensor_size, factor)[0]
    levels = pixel_levels(events, w, state.level.shape[0] // w, state.level)  # stacked: more rows
    level_before = torch.empty_like(levels.level).scatter_(0, levels.order,
                                                           levels.level - levels.step)
    new_levels = levels.new_state
    del levels
    rx, ry = region_of(events, factor)
    ry *= out_w
    region, order = stable_sort_small(ry.add_(rx), state.index.shape[0])
    groups = RegionGroups(order, region, changes(region))
    del rx, ry, order
    firsts = where_true(groups.first)
    rank = run_index(groups.first)
    touched = take(region, firsts)

    # Anchor: each touched region's sum recomputed from the integer levels before the piece.
    ids, inside = region_pixels(touched, sensor_size, factor)
    m, anchor = log_mean_exp(state.level[ids], inside, contrast)
    del ids, inside

    # Change of the region's sum at each event, relative to its brightest anchored pixel.
    on = take(events.p, groups.order)
    before = take(level_before, groups.order)
    before -= take(m, rank)
    del level_before
    change, too_bright = _sum_changes(before, on, contrast)
    del before
    sums = _segment_sum(change, firsts, rank)
    total = sums.total
    # Error bound of each running sum: a few ulps of every term (anchor and changes) so far.
    # First a cheap one (all the region's changes in the piece), the exact one where it fails.
    tolerance = max(1e-10 * threshold, 16 * EPS)
    magnitude = torch.zeros_like(anchor).index_add_(0, rank, change.abs_()).add_(anchor)
    del change
    total += take(anchor, rank)
    lowest = torch.full_like(anchor, math.inf).scatter_reduce_(0, rank, total, "amin")
    bad = too_bright
    if not bool((magnitude.mul_(4 * EPS) <= lowest.mul_(tolerance)).all()):  # NaN fails too
        bound = _running_magnitude(sums, firsts, rank).add_(take(anchor, rank)).mul_(4 * EPS)
        bad = ~(bound <= total * tolerance) if bad is None else bad | ~(bound <= total * tolerance)
        del bound
    del sums, magnitude, lowest
    n = events.num_events
    if n > 1 and bad is not None and bool(bad.any()):
        used = int(take(groups.order, where_true(bad)).min())
        if used == 0:  # the first event alone: its sum is the anchor plus one change
            return _events_piece(Events(*(column[:1] for column in events)), sensor_size,
                                 factor, contrast, threshold, state, emitted)
        # Keep the events before the cut (each region keeps a prefix of its own events).
        kept = where_true(groups.order < used)
        groups = RegionGroups(*(take(column, kept) for column in groups))
        region, total, rank = groups.region, take(total, kept), take(rank, kept)
        new_levels = state.level.clone()
        new_levels.index_add_(0, events.y[:used] * w + events.x[:used],
                              events.p[:used].to(torch.int64).mul_(2).sub_(1))
        events = Events(*(column[:used] for column in events))
        n = used
        firsts = where_true(groups.first)

    # u = log(I_r) / theta = (c * m + log(sum / n_r)) / theta, then the reference rule.
    # Per region: c * m / theta - log(n_r) / theta, added to log(sum) / theta.
    log_pixels = region_pixel_count(touched, sensor_size, factor).to(torch.float64).log_()
    offset = m.to(torch.float64).mul_(contrast / threshold).sub_(log_pixels.div_(threshold))
    u = torch.log(total).div_(threshold).add_(take(offset, rank))
    floor_u, on_level = snap(u)
    del u, total
    q = reference_index(floor_u, on_level, groups.first, take(state.index, region))
    q_before = q.roll(1)
    q_before[firsts] = take(state.index, take(region, firsts))
    cross = crossings(q_before, q, emitted=emitted)

    # Back to time order: crossings of one step keep their level order.
    source, by_time = stable_sort_small(take(groups.order, cross.step), n)
    out_x, out_y = region_xy(take(region, take(cross.step, by_time)), out_w)
    out = Events(out_x, out_y, take(events.t, source), take(cross.on, by_time))

    lasts = torch.cat([firsts[1:] - 1, firsts.new_tensor([n - 1])])
    new_index = state.index.clone()
    new_index.scatter_(0, take(region, lasts), take(q, lasts))
    return out, PhotocurrentState(new_levels, new_index, events.t[-1].clone()), n
