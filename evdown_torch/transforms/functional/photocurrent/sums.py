"""Running photocurrent sums of the photocurrent events mode (docs/semantics.md, method 7).

Per piece of a stream: each event's pixel level before it, grouped by region with a one-byte
sort (:func:`grouped_levels`); each touched region anchored at its brightest pixel (and
anchored again each time its pixels climb :data:`MAX_EXPONENT` higher, :func:`rising_anchors`),
and every intensity ``exp(c * (L - m_r))`` in two-word int64 fixed point (:func:`fixed_point`),
so that the region's sum after each event is an exact integer running sum in which a pixel's
changes telescope to its current intensity (:func:`running_sums`, with the zero-sum segmented
cumulative sum :func:`zero_sum_cumsum`). The error is a few ulps of each current sum plus
half a fine unit per pixel, however many events the piece has. The one-word sums a long
piece tries first are in :mod:`.one_word`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import (
    RADIX_SORT_MIN,
    changes,
    continued_cumsum,
    divide,
    last_of_runs,
    run_index,
    stable_sort_small,
    take,
    where_true,
)

#: Largest exponent ``c * (L - m_r)`` above its anchor a pixel may reach: the fixed point's
#: scale is fitted to the brightest intensity of the piece, so a pixel rising far above its
#: region's anchor would coarsen every region's fine unit (``2**-65`` of an anchor at 32).
#: The two-word sums take a new anchor there (:func:`rising_anchors`); the one-word sums
#: hand such regions over to them (:class:`.one_word.TooBright`).
MAX_EXPONENT = 32.0

#: Unit roundoff of float64.
EPS = 2.0**-53


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
        pixel_on: ``(N,)`` int64 (or int32, when every level and id fits) ``2 * (y * W + x) +
            on`` of each event (``on``: 1 for ON, 0 for OFF), grouped by region, time order
            inside a region; overwritten.
        place: ``(N,)`` uint8 (or int64 when ``bound > 256``) key in ``[0, bound)`` as above,
            or ``None`` when every region is one pixel.
        bound: bound of ``place``.
        levels: ``(H * W,)`` int64 pixel levels before the events.

    Returns:
        ``(key, new_levels)``: ``(N,)`` ``2 * L + on`` in ``pixel_on``'s dtype, ``L`` the
        level of the event's pixel just before it, and a new ``(H * W,)`` int64 tensor of the
        levels after all the events.
    """
    n = pixel_on.shape[0]
    perm = None
    if place is not None:  # one look-up of the packed pixel and polarity: far cheaper than two
        if place.dtype == torch.uint8 and n >= RADIX_SORT_MIN:
            perm = torch.sort(place, stable=True).indices
        else:
            perm = stable_sort_small(place, bound)[1]
        pixel_on = take(pixel_on, perm)
    dtype = pixel_on.dtype  # int32 where the caller found every level fits
    on = torch.bitwise_and(pixel_on, 1)
    change = torch.mul(on, 2).sub_(1)
    pixel = pixel_on.bitwise_right_shift_(1)
    starts = where_true(changes(pixel))
    last = last_of_runs(starts, n)
    pixel = take(pixel, starts).long()
    after, final = continued_cumsum(change, starts, last, take(levels, pixel).to(dtype))
    # The level after each event, then 2 * (after - s) + on = 2 * after - 3 * on + 2 with the
    # change s = 2 * on - 1: the level before it, packed with its polarity.
    key = after.mul_(2).add_(2).sub_(on, alpha=3)
    del change, after, on
    new_levels = levels.clone()
    new_levels.scatter_(0, pixel, final.long())
    if perm is None:
        return key, new_levels
    return torch.empty_like(key).scatter_(0, perm, key), new_levels


def zero_sum_cumsum(
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


def intensity_words(
    j: Tensor, contrast: float, scale: float, fine: float
) -> tuple[Tensor, Tensor]:
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
    """Intensities of a piece in two-word fixed point.

    ``exp(c * j) * scale ~ high + low / fine`` (the error below ``1 / (2 * fine)``): integer
    sums are exact, and a pixel's changes telescope to its current intensity however many
    events it has.
    """

    anchor: tuple[Tensor, Tensor]  # (S,) int64 sums of each region's pixels' (high, low)
    change: tuple[Tensor, Tensor]  # (N,) int64 change of (high, low) at each event


def key_levels(key: Tensor) -> tuple[Tensor, Tensor]:
    """Each event's pixel level before it and its change (+1, -1), from ``key = 2 * L + on``.

    Example:
        >>> [t.tolist() for t in key_levels(torch.tensor([1, 4, -3]))]
        [[0, 2, -2], [1, -1, 1]]
    """
    before = divide(key, 2)
    return before, (key - 2 * before).mul_(2).sub_(1)


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
        lo: lower bound of ``j``.
        hi: upper bound of ``j``.
        contrast: ``c``.
        scale: power of two scaling the intensities (``high``).
        fine: power of two, the ``low`` word's units per unit of ``high``.
    """

    def region_sums(values: Tensor) -> Tensor:
        return (values if inside is None else values.masked_fill_(~inside, 0)).sum(1)

    if hi - lo + 3 <= TABLE_SIZE:  # a table of intensities, then look-ups
        words = intensity_words(torch.arange(lo - 1, hi + 2, device=key.device), contrast, scale,
                                fine)
        index = pixel_j.sub_(lo - 1).view(-1)
        anchor_high, anchor_low = (region_sums(take(word, index).view_as(pixel_j))
                                   for word in words)
        # Row i (j = lo + i): [change by OFF, change by ON].
        index = key.sub_(2 * lo)
        change_high, change_low = (
            take(torch.stack([word[:-2] - word[1:-1], word[2:] - word[1:-1]], 1).reshape(-1),
                 index)
            for word in words)
        return FixedPoint((anchor_high, anchor_low), (change_high, change_low))
    anchor_high, anchor_low = (region_sums(word)
                               for word in intensity_words(pixel_j, contrast, scale, fine))
    before, change = key_levels(key)
    after = before + change
    change_high, change_low = (
        a.sub_(b) for a, b in zip(intensity_words(after, contrast, scale, fine),
                                  intensity_words(before, contrast, scale, fine),
                                  strict=True))
    return FixedPoint((anchor_high, anchor_low), (change_high, change_low))


def brightest_level(contrast: float) -> int:
    """Highest level above its anchor a pixel may reach in a piece.

    Its intensity stays within :data:`MAX_EXPONENT` log units of the anchor's (one level at
    least, for contrasts above :data:`MAX_EXPONENT`).
    """
    return max(math.floor(MAX_EXPONENT / contrast) - 1, 0)


def two_word_scale(
    hi: int, per_region: int, contrast: float, threshold: float
) -> tuple[float, float, float]:
    """``(scale, fine, lowest)`` of :func:`running_sums` for pixels up to ``hi`` above anchors.

    ``scale`` and ``fine`` keep a region's sum of either word below ``2**61``; ``lowest`` is
    the smallest sum the two words hold to ``1e-10 * threshold`` (error bound of each sum: a
    few ulps of every intensity, see :func:`intensity_words`, and of the conversions, and half
    a fine unit of the fine word per pixel).
    """
    top = max(math.exp(contrast * (hi + 1)), 1.0)
    bits = 61 - (2 * per_region).bit_length()
    scale = math.ldexp(1.0, bits - math.frexp(top)[1])
    fine = math.ldexp(1.0, bits)
    slack = 6
    tolerance = max(1e-10 * threshold, 4 * slack * EPS)
    return scale, fine, per_region / (2 * fine * scale) / (tolerance - slack * EPS)


class RunningSums(NamedTuple):
    """What :func:`running_sums` gives for a piece.

    Each region's events are summed against one anchor, or against several where its pixels
    climb more than :data:`MAX_EXPONENT` during the piece (:func:`rising_anchors`).

    Attributes:
        anchor: ``(G,)`` int64 level of each anchor.
        anchor_region: ``(G,)`` int64 rank of each anchor's region among the touched regions,
            or ``None`` where each region has one anchor (``G = S``, in region order).
        anchor_of: ``(N,)`` int64 anchor of each event.
        total: ``(N,)`` float64 ``sum exp(c * (L_p - anchor))`` over the region after each
            event.
        bad: ``None``, or an ``(N,)`` bool mask of the events the sums cannot hold (a sum
            below what the fixed point resolves to the tolerance); only the events of a region
            before its first of those are valid.
    """

    anchor: Tensor
    anchor_region: Tensor | None
    anchor_of: Tensor
    total: Tensor
    bad: Tensor | None


def running_sums(
    key: Tensor, ids: Tensor, inside: Tensor | None, levels: Tensor, firsts: Tensor,
    lasts: Tensor, rank: Tensor, per_region: int, contrast: float, threshold: float,
    slot: Callable[[], Tensor],
) -> RunningSums:
    """Each region's anchors and its sum after each of its events, for a piece of ``N > 1``.

    Args:
        key: ``(N,)`` int64 ``2 * L + on`` of each event (``L``: its pixel's level before it),
            grouped by region; overwritten.
        ids: ``(S, n)`` int64 pixel ids of the touched regions (:func:`region_pixel_ids`).
        inside: their mask (``None``: all inside).
        levels: ``(H * W,)`` int64 pixel levels before the piece.
        firsts: ``(S,)`` int64 first position of each region's events.
        lasts: ``(S,)`` int64 last position of each region's events.
        rank: ``(N,)`` int64 region (segment) of each event.
        per_region: ``fx * fy``.
        contrast: ``c``.
        threshold: ``theta``.
        slot: gives the ``(N,)`` int64 column of each event's pixel in ``ids``, called only
            where a pixel climbs more than :data:`MAX_EXPONENT` above its region's anchor: the
            region then takes a new anchor there (:func:`rising_anchors`).

    Returns:
        The :class:`RunningSums`; each region's first anchor is its brightest level before
        the piece.
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
    key -= take((m * 2).to(key.dtype), rank)
    brightest = brightest_level(contrast)
    anchor_region = anchor_of = None
    lo, hi = (int(v) // 2 for v in torch.aminmax(key))
    if hi > brightest:  # climbing regions: new anchors
        rising = rising_anchors(key, rank, firsts, pixel_j, slot(), brightest + 1)
        anchor_of, anchor_region, firsts = rising.anchor_of, rising.region, rising.firsts
        key -= take((2 * rising.level).to(key.dtype), anchor_of)
        pixel_j = rising.pixel_level.sub_(rising.level[:, None])
        if inside is not None:
            inside = take(inside, anchor_region)
            pixel_j.masked_fill_(~inside, 0)
        m = take(m, anchor_region).add_(rising.level)
        rank, lasts = anchor_of, last_of_runs(firsts, key.shape[0])
        lo, hi = (int(v) // 2 for v in torch.aminmax(key))
    # (Every anchor is a level some pixel of its region is at when the anchor is taken.)
    lowest_j, highest_j = (int(v) for v in torch.aminmax(pixel_j))
    lo, hi = min(lo, lowest_j), max(hi, highest_j)
    darkest = -math.ceil(800 / contrast)  # exp(c * j) is 0 for j <= darkest + 1
    if lo < darkest:
        key.clamp_(min=2 * darkest)
        pixel_j.clamp_(min=darkest)
        lo = darkest
    bad = None  # (hi <= brightest: the anchors climb with the pixels)
    scale, fine, lowest = two_word_scale(hi, per_region, contrast, threshold)
    sums = fixed_point(key, pixel_j, inside, lo, hi, contrast, scale, fine)
    del pixel_j
    # The region's sum after each event.
    high, low = (zero_sum_cumsum(change, anchor, firsts, lasts, rank)
                 for anchor, change in zip(sums.anchor, sums.change, strict=True))
    del sums
    total = low.to(torch.float64).mul_(1 / (fine * scale)).add_(high, alpha=1 / scale)
    del high, low

    if not float(total.min()) >= lowest:  # NaN fails too
        weak = ~(total >= lowest)
        bad = weak if bad is None else bad | weak
    if bad is not None and not bool(bad.any()):
        bad = None
    return RunningSums(m, anchor_region, rank if anchor_of is None else anchor_of, total, bad)


class RisingAnchors(NamedTuple):
    """Anchors of climbing regions (:func:`rising_anchors`), relative to the first anchors.

    Attributes:
        level: ``(G,)`` int64 level of each anchor, ``k * step``.
        region: ``(G,)`` int64 region (rank) of each anchor.
        firsts: ``(G,)`` int64 first event of each anchor's run.
        anchor_of: ``(N,)`` int64 anchor of each event.
        pixel_level: ``(G, n)`` int64 levels of the region's pixels just before each run.
    """

    level: Tensor
    region: Tensor
    firsts: Tensor
    anchor_of: Tensor
    pixel_level: Tensor


def rising_anchors(
    key: Tensor, rank: Tensor, firsts: Tensor, pixel_j: Tensor, slot: Tensor, step: int
) -> RisingAnchors:
    """Split each region's events into runs whose pixels stay below ``step`` above an anchor.

    Levels are relative to each region's brightest before the piece (0). Before event ``e``,
    no pixel of its region is above ``R(e)``: the highest level a pixel of the region has
    had so far (0 before the piece, then the level after each earlier event, a running
    maximum). The event's run is ``k = R(e) // step`` of its region, anchored at
    ``k * step``: every level before an event of the run, and every pixel's level at the
    run's start, is at most ``step - 1`` above it. Runs and anchors come from one cumulative
    maximum, and the pixels' levels at each run's start from the changes of the runs before
    it; no loop over regions or runs.

    Args:
        key: ``(N,)`` ``2 * j + on`` of each event (``j``: its pixel's level before it,
            relative to its region's brightest before the piece), grouped by region.
        rank: ``(N,)`` int64 region of each event, ascending.
        firsts: ``(S,)`` int64 first event of each region.
        pixel_j: ``(S, n)`` int64 levels of each region's pixels before the piece, relative
            as ``key``.
        slot: ``(N,)`` int64 column of each event's pixel in ``pixel_j``.
        step: ``>= 1`` levels between anchors.

    Example:
        >>> key = torch.tensor([1, 3, 5, 7, 8])  # one pixel: 0 -> 1 -> 2 -> 3 -> 4 -> 3
        >>> r = rising_anchors(key, torch.zeros(5, dtype=torch.int64), torch.tensor([0]),
        ...                    torch.tensor([[0, -1]]), torch.zeros(5, dtype=torch.int64), 2)
        >>> r.level.tolist(), r.anchor_of.tolist(), r.pixel_level.tolist()
        ([0, 2, 4], [0, 0, 1, 1, 2], [[0, -1], [2, -1], [4, -1]])
    """
    key = key.long()
    before, change = key_levels(key)
    after = before + change
    # R(e): a running maximum of the levels after each event (from 0: levels below count as
    # 0, and a piece climbs at most one level an event), kept inside each region by lifting
    # every region's values above the previous region's (below N**2: no overflow).
    after.clamp_(min=0)
    lift = rank * (int(after.max()) + 1)
    climbed = torch.cummax(after.add_(lift), 0).values.sub_(lift)
    reach = torch.zeros_like(climbed)
    reach[1:] = climbed[:-1]
    reach.index_fill_(0, firsts, 0)
    k = divide(reach, step)
    starts = changes(k).index_fill_(0, firsts, True)
    run_firsts = where_true(starts)
    anchor_of = run_index(starts)
    region = take(rank, run_firsts)
    runs, width = run_firsts.shape[0], pixel_j.shape[1]
    # Each pixel's level at a run's start: its level before the piece plus the changes of
    # its events in the region's runs before (an exclusive sum over runs, restarted per region).
    moved = torch.zeros(runs * width, dtype=torch.int64, device=key.device)
    moved.index_add_(0, anchor_of * width + slot, change)
    moved = moved.view(runs, width)
    done = moved.cumsum(0).sub_(moved)
    done -= take(done, take(take(anchor_of, firsts), region))
    pixel_level = take(pixel_j, region).add_(done)
    return RisingAnchors(take(k, run_firsts).mul_(step), region, run_firsts, anchor_of,
                         pixel_level)
