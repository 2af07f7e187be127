"""Photocurrent pooling kernels (SEMANTICS.md method 7): events to video to events.

Each input pixel keeps an integer level ``L_p`` (ON +1, OFF -1) and its log intensity is
``c * L_p``. A region's photocurrent is the mean of its pixels' intensities,
``I_r = (1 / n_r) * sum exp(c * L_p)``, and the output pixel runs the DVS reference rule on
``log I_r`` at contrast ``theta``: with ``u = log(I_r) / theta``, the shared rule of
:mod:`~evdown_torch.transforms.functional._reference` (floor of ``u`` and whether ``u`` is on a
level, a ``u`` within :data:`~evdown_torch.transforms.functional._knots.SNAP` of an integer
counting as on it).

*Events mode* (:func:`photocurrent_events`): ``log I_r`` changes only at input events. The
stream goes in pieces (about 16 events per pixel, at most :data:`CHUNK_EVENTS`). In a piece,
one sort groups the events by region (time order inside) and a one-byte sort of that order by
the pixel's place in its region groups them by pixel, which gives every pixel's exact int64
level before each of its events (:func:`grouped_levels`). Each touched region is *anchored* at
its brightest pixel ``m_r`` at the start of the piece, and every intensity ``exp(c * (L -
m_r))`` is written in two-word int64 fixed point (:func:`fixed_point`): the region's sum after
each event is the anchor's sum plus a running sum of integer changes, exact, in which a
pixel's changes telescope to its current intensity however many events it has, and regions
do not mix (:func:`_zero_sum_cumsum`). The only errors are a few ulps of each current intensity
and half a step of the fine word per pixel. Where that bound would exceed ``1e-10 * theta`` of
the sum (all of a region's pixels falling some 50 log units below its anchor), or a pixel rises
more than :data:`MAX_EXPONENT` above its anchor, the piece is cut before that event and the
rest re-anchored; a piece cut down to one event takes its region's sum straight from the
levels after it.

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
    RADIX_SORT_MIN,
    changes,
    divide,
    ends,
    region_of,
    region_pixel_count,
    region_xy,
    sort_by_time,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.checks import output_size
from evdown_torch.events import Events
from evdown_torch.transforms.functional._reference import (
    SNAP,
    crossings,
    reference_index,
)

#: Largest exponent ``c * (L - m_r)`` a piece may reach before it is cut: the fixed point's
#: scale is fitted to the brightest intensity of the piece, so a pixel rising far above its
#: region's anchor would coarsen every region's fine step (``2**-65`` of an anchor at 32).
MAX_EXPONENT = 32.0

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
    offset = u - nearest
    on_level = offset.abs() <= SNAP
    # Below the nearest integer by more than SNAP (|offset| <= 1/2): floor(u) = nearest - 1.
    return nearest.sub_(offset.lt_(-SNAP)).to(torch.int64), on_level


def region_pixels(
    regions: Tensor, sensor_size: tuple[int, int, int], factor: tuple[int, int]
) -> tuple[Tensor, Tensor | None]:
    """Pixel ids ``y * W + x`` of every pixel of ``regions``: ``(R, fx * fy)`` int64 and a
    same-shaped bool mask of those inside the sensor (ids outside are 0), ``None`` when the
    factor divides the sensor (every pixel is inside). Regions of stacked recordings (ids past
    ``Ho * Wo``) are inside where their recording's are."""
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


def log_mean_exp(
    levels: Tensor, inside: Tensor | None, contrast: float
) -> tuple[Tensor, Tensor]:
    """Per row: brightest level ``m`` and ``sum exp(c * (L - m))`` over the ``inside`` entries.

    Args:
        levels: ``(R, n)`` int64 pixel levels.
        inside: ``(R, n)`` bool, the entry is a sensor pixel (``None``: all are).
        contrast: ``c``.

    Returns:
        ``(m, s)``: ``(R,)`` int64 and ``(R,)`` float64 in ``[1, n]``.
    """
    if inside is None:
        m = levels.amax(1)
        return m, torch.exp((levels - m[:, None]).to(torch.float64).mul_(contrast)).sum(1)
    lowest = torch.iinfo(torch.int64).min
    m = torch.where(inside, levels, lowest).amax(1)
    below = torch.where(inside, levels - m[:, None], 0).to(torch.float64).mul_(contrast)
    return m, torch.where(inside, torch.exp(below), 0.0).sum(1)


#: Largest table of ``exp(c * j)`` values :func:`fixed_point` builds instead of calling exp
#: per event.
TABLE_SIZE = 1 << 16


def grouped_levels(
    pixel_on: Tensor, place: Tensor | None, bound: int, levels: Tensor
) -> tuple[Tensor, Tensor]:
    """``2 * level + on`` of each event's pixel just before it, for events grouped by region.

    A stable sort of the events by a small key ``place`` groups them by pixel: events of one
    pixel share a key and distinct pixels of one region have distinct keys, so in ``(place,
    region, time)`` order each pixel's events are consecutive. With at most 256 keys (the
    pixel's place in its region, plus a few bits of the region so that a key's events stay
    close together in memory) it is a one-byte sort: no second sort over all pixels.

    Args:
        pixel_on: ``(N,)`` int64 ``2 * (y * W + x) + on`` of each event (``on``: 1 for ON, 0
            for OFF), grouped by region, time order inside a region; overwritten.
        place: ``(N,)`` uint8 (or int64 when ``bound > 256``) key in ``[0, bound)`` as above,
            or ``None`` when every region is one pixel.
        bound: bound of ``place``.
        levels: ``(H * W,)`` int64 pixel levels before the events.

    Returns:
        ``(key, new_levels)``: ``(N,)`` int64 ``2 * L + on`` with ``L`` the level of the
        event's pixel just before it, and a new ``(H * W,)`` tensor of the levels after all
        the events.
    """
    n = pixel_on.shape[0]
    perm = None
    if place is not None:  # one look-up of the packed pixel and polarity: far cheaper than two
        if place.dtype == torch.uint8 and n >= RADIX_SORT_MIN:
            perm = torch.sort(place, stable=True).indices
        else:
            perm = stable_sort_small(place, bound)[1]
        pixel_on = take(pixel_on, perm)
    on = torch.bitwise_and(pixel_on, 1)
    step = torch.mul(on, 2).sub_(1)
    pixel = pixel_on.bitwise_right_shift_(1)
    starts = where_true(changes(pixel))
    last = torch.cat([starts[1:] - 1, starts.new_tensor([n - 1])])
    pixel = take(pixel, starts)
    # One cumulative sum whose first step of each pixel also moves from the previous pixel's
    # last level to this pixel's starting level (a telescoping correction).
    plain = torch.cumsum(step, 0)
    first_level = take(levels, pixel)
    final = take(plain, last) - take(plain, starts) + take(step, starts) + first_level
    del plain
    jump = first_level
    jump[1:] -= final[:-1]
    before = step.index_add(0, starts, jump).cumsum_(0).sub_(step)
    del step
    key = on.add_(before, alpha=2)
    del before
    new_levels = levels.clone()
    new_levels.scatter_(0, pixel, final)
    if perm is None:
        return key, new_levels
    return torch.empty_like(key).scatter_(0, perm, key), new_levels


def _zero_sum_cumsum(
    values: Tensor, start: Tensor, firsts: Tensor, lasts: Tensor, rank: Tensor
) -> Tensor:
    """Running sums ``start + cumsum(values)`` restarting at each segment (runs of ``rank``).

    Each segment's last value is lowered by the segment's total before one global cumulative
    sum, so that the global sum returns to 0 after every segment: its partial sums never
    exceed one segment's (exact for int64 that fit). ``values`` is overwritten.

    Args:
        values: ``(N,)`` values, overwritten.
        start: ``(S,)`` value of each segment before its first element.
        firsts: ``(S,)`` int64 first position of each segment.
        lasts: ``(S,)`` int64 last position of each segment.
        rank: ``(N,)`` int64 segment of each element, ascending.
    """
    values.index_add_(0, firsts, start)
    total = torch.zeros_like(start).index_add_(0, rank, values)
    values.index_add_(0, lasts, total.neg())
    return values.cumsum_(0).index_copy_(0, lasts, total)


def _split(j: Tensor, contrast: float, scale: float, fine: float) -> tuple[Tensor, Tensor]:
    """``exp(c * j) * scale`` of int64 ``j`` in two int64 words: ``high + low / fine``.

    ``c * j`` is rarely a float; ``exp(c * j)`` is taken as ``exp(c_hi * j) * exp(c_lo * j)``
    with ``c_hi`` (``c`` to 22 bits) times ``|j| < 2**31`` exact and ``c_lo * j`` tiny, so the
    intensity is within 3 ulps of the exact value however large ``|c * j|`` is.
    """
    mantissa, exponent = math.frexp(contrast)
    c_hi = math.ldexp(math.floor(math.ldexp(mantissa, 22)), exponent - 22)
    j = j.to(torch.float64)
    scaled = torch.exp(j * c_hi).mul_(torch.exp(j.mul_(contrast - c_hi))).mul_(scale)
    high = torch.round(scaled)
    low = torch.round(scaled.sub_(high).mul_(fine))
    return high.to(torch.int64), low.to(torch.int64)


class FixedPoint(NamedTuple):
    """Intensities of a piece in two-word fixed point, ``exp(c * j) * scale ~ high + low /
    fine`` (the error below ``1 / (2 * fine)``): integer sums are exact, and a pixel's
    changes telescope to its current intensity however many events it has."""

    anchor: tuple[Tensor, Tensor]  # (S,) int64 sums of each region's pixels' (high, low)
    change: tuple[Tensor, Tensor]  # (N,) int64 change of (high, low) at each event


def fixed_point(
    key: Tensor, pixel_j: Tensor, inside: Tensor | None, lo: int, hi: int, contrast: float,
    scale: float, fine: float,
) -> FixedPoint:
    """The :class:`FixedPoint` sums of the anchors and changes of the events.

    Args:
        key: ``(N,)`` int64 ``2 * j + on`` of each event, ``j`` the level of its pixel before
            it relative to its region's anchor, in ``[lo, hi]`` (``on``: 1 ON, 0 OFF);
            overwritten.
        pixel_j: ``(S, n)`` int64 level of every pixel of each region relative to its anchor,
            in ``[lo, hi]``; overwritten.
        inside: ``(S, n)`` bool, the entry is a sensor pixel (``None``: all are).
        lo, hi: bounds of ``j``.
        contrast: ``c``.
        scale, fine: powers of two.
    """

    def region_sums(values: Tensor) -> Tensor:
        return (values if inside is None else values.masked_fill_(~inside, 0)).sum(1)

    if hi - lo + 3 <= TABLE_SIZE:  # a table of intensities, then look-ups
        words = _split(torch.arange(lo - 1, hi + 2, device=key.device), contrast, scale, fine)
        index = pixel_j.sub_(lo - 1).view(-1)
        anchor = tuple(region_sums(take(word, index).view_as(pixel_j)) for word in words)
        # Row i (j = lo + i): [change by OFF, change by ON].
        index = key.sub_(2 * lo)
        change = tuple(take(torch.stack([word[:-2] - word[1:-1], word[2:] - word[1:-1]], 1)
                            .reshape(-1), index) for word in words)
        return FixedPoint(anchor, change)
    anchor = tuple(region_sums(word) for word in _split(pixel_j, contrast, scale, fine))
    before = divide(key, 2)
    after = torch.where(key - 2 * before == 1, before + 1, before - 1)
    change = tuple(a.sub_(b) for a, b in zip(_split(after, contrast, scale, fine),
                                              _split(before, contrast, scale, fine),
                                              strict=True))
    return FixedPoint(anchor, change)


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
    # Untouched pixels keep levels already checked: the events' pixels bound the new ones.
    touched = take(state.level, events.y * sensor_size[0] + events.x)
    check_level_range(int(touched.abs().max()) + n, contrast, threshold)
    del touched
    outputs = []
    # Pieces of about 16 events per pixel: re-anchoring then costs little (at most the
    # sensor's pixels per piece) and a small sensor's pieces stay in the CPU's caches.
    largest = min(max(16 * sensor_size[0] * sensor_size[1], 1 << 16), CHUNK_EVENTS)
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


def _running_sums(
    key: Tensor, ids: Tensor, inside: Tensor | None, levels: Tensor, firsts: Tensor,
    lasts: Tensor, rank: Tensor, per_region: int, contrast: float, threshold: float,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Each region's anchor and its sum after each of its events, for a piece of ``N > 1``.

    Args:
        key: ``(N,)`` int64 ``2 * L + on`` of each event (``L``: its pixel's level before it),
            grouped by region; overwritten.
        ids: ``(S, n)`` int64 pixel ids of the touched regions (:func:`region_pixels`).
        inside: their mask (``None``: all inside).
        levels: ``(H * W,)`` int64 pixel levels before the piece.
        firsts, lasts: ``(S,)`` int64 first and last position of each region's events.
        rank: ``(N,)`` int64 region (segment) of each event.
        per_region: ``fx * fy``.
        contrast, threshold: ``c`` and ``theta``.

    Returns:
        ``(m, total, bad)``: ``(S,)`` int64 brightest level of each region before the piece,
        ``(N,)`` float64 ``sum exp(c * (L_p - m))`` over the region after each event, and
        ``None``, or an ``(N,)`` bool mask of the events the sums cannot hold (a pixel more
        than :data:`MAX_EXPONENT` above its anchor, or a sum below what the fixed point
        resolves to the tolerance); only the events before the first of those are valid.
    """
    # Anchor: each touched region's brightest pixel m before the piece, and every pixel's
    # level relative to it (j <= 0); the same j of each event's pixel before it, in
    # key = 2 * j + on.
    pixel_j = take(levels, ids.view(-1)).view_as(ids)
    if inside is None:
        m = pixel_j.amax(1)
    else:
        m = pixel_j.masked_fill(~inside, torch.iinfo(torch.int64).min).amax(1)
    pixel_j -= m[:, None]
    if inside is not None:
        pixel_j.masked_fill_(~inside, 0)
    key -= take(m * 2, rank)
    lo, hi = (int(v) // 2 for v in torch.aminmax(key))
    lo, hi = min(lo, int(pixel_j.min())), max(hi, 0)
    darkest = -math.ceil(800 / contrast)  # exp(c * j) is 0 for j <= darkest + 1
    if lo < darkest:
        key.clamp_(min=2 * darkest)
        pixel_j.clamp_(min=darkest)
        lo = darkest
    # A pixel may end a step at most MAX_EXPONENT above its anchor (one level at least, for
    # contrasts above MAX_EXPONENT).
    brightest = max(math.floor(MAX_EXPONENT / contrast) - 1, 0)
    bad = None
    if hi > brightest:  # a pixel too far above its anchor: cut before its event
        bad = key > 2 * brightest + 1
        key.clamp_(max=2 * brightest + 1)
        hi = brightest
    # Two-word fixed point: a region's sum of either word stays below 2**61.
    top = max(math.exp(contrast * (hi + 1)), 1.0)
    bits = 61 - (2 * per_region).bit_length()
    scale = math.ldexp(1.0, bits - math.frexp(top)[1])
    fine = math.ldexp(1.0, bits)
    sums = fixed_point(key, pixel_j, inside, lo, hi, contrast, scale, fine)
    del pixel_j
    # The region's sum after each event, times scale.
    high, low = (_zero_sum_cumsum(change, anchor, firsts, lasts, rank)
                 for anchor, change in zip(sums.anchor, sums.change, strict=True))
    del sums
    total = low.to(torch.float64).mul_(1 / fine).add_(high)
    del high, low

    # Error bound of each sum (in units of 1 / scale): a few ulps of every intensity (exp,
    # see _split, and the conversions) and half a step of the fine word per pixel.
    slack = 6
    tolerance = max(1e-10 * threshold, 4 * slack * EPS)
    lowest = per_region / (2 * fine) / (tolerance - slack * EPS)  # the smallest sum held
    if not float(total.min()) >= lowest:  # NaN fails too
        weak = ~(total >= lowest)
        bad = weak if bad is None else bad | weak
    if bad is not None and not bool(bad.any()):
        bad = None
    return m, total.mul_(1 / scale), bad


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
    w = sensor_size[0]
    fx, fy = factor
    out_w = output_size(sensor_size, factor)[0]
    per_region = fx * fy
    n = events.num_events
    rx, ry = region_of(events, factor)
    pixel_on = torch.add(events.x, events.y, alpha=w).mul_(2).add_(events.p)
    place, bound = None, 1
    if per_region > 1:  # the pixel's place in its region, and a few high bits of the region
        chunks = max(1, 256 // per_region)
        bound = chunks * per_region
        shift = max(0, (state.index.shape[0] - 1).bit_length() - (chunks.bit_length() - 1))
        place = torch.add(events.x, rx, alpha=-fx)
        place.add_(events.y, alpha=fx).add_(ry, alpha=-fx * fy)
    ry.mul_(out_w).add_(rx)
    # Region ids stay int32 when they were sorted as such (look-ups take int32 indices).
    regions = state.index.shape[0]
    region, order = stable_sort_small(ry, regions, int64_keys=regions <= 1 << 15)
    if place is not None:
        place.add_(ry.bitwise_right_shift_(shift), alpha=per_region)
        place = take(place.to(torch.uint8) if bound <= 256 else place, order)
    del rx, ry
    first = changes(region)
    firsts = where_true(first)
    lasts = torch.cat([firsts[1:] - 1, firsts.new_tensor([n - 1])])
    rank = torch.cumsum(first, 0, dtype=torch.int64).sub_(1)
    touched = take(region, firsts).long()
    key, new_levels = grouped_levels(take(pixel_on, order), place, bound, state.level)
    del place, pixel_on

    ids, inside = region_pixels(touched, sensor_size, factor)
    if n == 1:  # a lone event (after a cut): its region's sum straight from the levels after it
        m, total = log_mean_exp(new_levels[ids], inside, contrast)
        bad = None
    else:
        m, total, bad = _running_sums(key, ids, inside, state.level, firsts, lasts, rank,
                                      per_region, contrast, threshold)
    del ids, inside, key
    if bad is not None:  # the running sums cannot hold an event: cut the piece before it
        used = int(take(order, where_true(bad)).min())
        if used == 0:
            return _events_piece(Events(*(column[:1] for column in events)), sensor_size,
                                 factor, contrast, threshold, state, emitted)
        # Keep the events before the cut (each region keeps a prefix of its own events).
        kept = where_true(order < used)
        order, region, total = take(order, kept), take(region, kept), take(total, kept)
        first, rank = take(first, kept), take(rank, kept)
        new_levels = state.level.clone()
        new_levels.index_add_(0, events.y[:used] * w + events.x[:used],
                              events.p[:used].to(torch.int64).mul_(2).sub_(1))
        events = Events(*(column[:used] for column in events))
        n = used
        firsts = where_true(first)
        lasts = torch.cat([firsts[1:] - 1, firsts.new_tensor([n - 1])])

    # u = log(I_r) / theta = (c * m + log(total / n_r)) / theta, then the reference rule.
    log_pixels = region_pixel_count(touched, sensor_size, factor).to(torch.float64).log_()
    offset = m.to(torch.float64).mul_(contrast).sub_(log_pixels)
    u = take(offset.div_(threshold), rank).add_(total.log_(), alpha=1 / threshold)
    floor_u, on_level = snap(u)
    del u, total
    # The reference rule on the steps that can change q only (a step that stays strictly
    # inside the cell its predecessor ended in keeps q and crosses nothing): a tenth or less
    # of the events when a level takes several events to cross.
    moved = changes(floor_u)
    moved |= first
    moved |= on_level
    moved[1:] |= on_level[:-1]
    kept = where_true(moved)
    del moved
    region, first = take(region, kept), take(first, kept)
    floor_u, on_level = take(floor_u, kept), take(on_level, kept)
    firsts = where_true(first)
    # Every region's q before the piece (a 0-d zero while all are 0: no look-up).
    q_start = take(state.index, region) if bool(state.index.any()) else first.new_zeros(
        (), dtype=torch.int64)
    q = reference_index(floor_u, on_level, first, q_start)
    del q_start, floor_u, on_level
    q_before = q.roll(1)
    q_before[firsts] = take(state.index, take(region, firsts))
    cross = crossings(q_before, q, emitted=emitted)

    # Back to time order: crossings of one step keep their level order.
    step = take(kept, cross.step)
    source, by_time = stable_sort_small(take(order, step), n)
    out_x, out_y = region_xy(take(region, take(cross.step, by_time)).long(), out_w)
    out = Events(out_x, out_y, take(events.t, source), take(cross.on, by_time))

    lasts = where_true(ends(first))
    new_index = state.index.clone()
    new_index.scatter_(0, take(region, lasts).long(), take(q, lasts))
    return out, PhotocurrentState(new_levels, new_index, events.t[-1].clone()), n
