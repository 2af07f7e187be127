"""The one-word running sums of the photocurrent events mode (docs/semantics.md, method 7).

A long piece is first tried with one int64 word per region sum (:func:`one_word_sums`): each
region's intensities relative to its brightest level during the piece, one table of
``exp(c * j)`` for all regions, and one cumulative sum. :func:`one_word_moves` then decides
every event whose ``u`` lies clear of the snap bounds by more than the sums' error bound, as
the two-word sums of :mod:`.sums` (:func:`.sums.running_sums`) would, and hands the piece
over to them where one lies within it (``None``) or where some regions climb too far for one
word (:class:`TooBright`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from evdown_torch._tensors import (
    divide,
    run_max,
    runs_of,
    take,
    telescoped_cumsum,
    where_true,
)
from evdown_torch.transforms.functional.photocurrent.levels import snap
from evdown_torch.transforms.functional.photocurrent.sums import (
    EPS,
    TABLE_SIZE,
    brightest_level,
    intensity_words,
    two_word_scale,
)
from evdown_torch.transforms.functional.reference import SNAP, moves_to_solve

__all__ = ["NEAR_CAP", "WORD_BITS", "OneWordSums", "TooBright", "one_word_moves",
           "one_word_sums"]

#: Largest error bound in ``u`` of :func:`one_word_sums` that its caller works with: events
#: this close to a level are solved on the few it keeps.
NEAR_CAP = 1e-2

#: Bits of :func:`one_word_sums`' fixed point: a region's intensities sum to an integer
#: below ``2**62``.
WORD_BITS = 62


class OneWordSums(NamedTuple):
    """Running photocurrent sums of a piece in one int64 word (:func:`one_word_sums`).

    ``total * exp(c * (top - m)) / 2**bits`` (``m``: the region's anchor, as in
    :func:`.sums.running_sums`) is within ``per_region / total + two_word_error + 16 * EPS`` of the
    sum :func:`.sums.running_sums` gives for the same event, relative to it.
    """

    region: Tensor  # (N,) int64 the segment (touched region) of each event
    top: Tensor  # (S,) int64 each region's highest level before an event, plus 1 (>= any)
    total: Tensor  # (N,) int64 sum of round(exp(c * (L_p - top)) * 2**bits) after each event
    bits: int
    smallest: int  # the smallest total
    two_word_error: float  # bound of the two-word sums' fine units, relative to their sum


class TooBright(NamedTuple):
    """:func:`one_word_sums`' answer where some regions rise too far above their anchors.

    Their pixels go more than :data:`~.sums.MAX_EXPONENT` above the regions' brightest
    before the piece (the two-word sums anchor them again as they climb,
    :func:`~.sums.rising_anchors`); the other regions can be decided without them.
    """

    regions: Tensor  # (S,) bool, the touched regions that rise too far


def one_word_sums(
    key: Tensor, ids: Tensor, inside: Tensor | None, levels: Tensor, new_levels: Tensor,
    firsts: Tensor, counts: Tensor, per_region: int, contrast: float, threshold: float,
) -> OneWordSums | TooBright | None:
    """Each region's sum after each of its events in one word, or ``None`` where it cannot.

    Each region's intensities are taken relative to its brightest level during the piece
    (``top``): one int64 table of ``round(exp(c * j) * 2**bits)`` for ``j <= 0`` serves all
    regions, each event's change is looked up in it, and one cumulative sum runs over the
    grouped events, its first change of each region also moving it from the previous region's
    last sum to this region's sum before the piece (a telescoping correction). Every partial
    sum is a region's sum, an integer below ``2**62``: the result is exact and independent of
    the order of the additions. Its error is half a unit per pixel plus a few ulps of each
    intensity (about ``1e-17`` of the region's brightest intensity), so it decides every
    event whose ``u`` does not lie within that error of a snap bound as
    :func:`.sums.running_sums` does, with one word instead of two.

    :class:`TooBright` where a pixel rises too far above its anchor (where
    :func:`~.sums.running_sums` would anchor its region again). ``None`` where a sum is too
    small for the two words, where a region's sum before or after the piece lies so far below
    its brightest (a rise or fall of some 200 levels at ``c = 0.2``) that the error bound
    exceeds :data:`NEAR_CAP`, or where the levels that count span more than
    :data:`.sums.TABLE_SIZE`: the caller then takes :func:`.sums.running_sums`.

    Args:
        key: ``(N,)`` int32 or int64 ``2 * L + on`` of each event (``L``: its pixel's level
            before it), grouped by region (not modified).
        ids: ``(S, n)`` int64 pixel ids of the touched regions (``region_pixel_ids``).
        inside: their mask (``None``: all inside).
        levels: ``(H * W,)`` int64 pixel levels before the piece.
        new_levels: ``(H * W,)`` int64 pixel levels after it.
        firsts: ``(S,)`` int64 first position of each region's events.
        counts: ``(S,)`` int64 number of events of each region.
        per_region: ``fx * fy``.
        contrast: ``c``.
        threshold: ``theta``.
    """
    lowest_level = torch.iinfo(torch.int64).min
    pixel = take(levels, ids.view(-1)).view_as(ids)
    if inside is not None:
        pixel.masked_fill_(~inside, lowest_level)
    m = pixel.amax(1)
    # The level after an ON at the highest level before an event, or the anchor's.
    top = run_max(key, firsts).long()
    top = torch.maximum(divide(top, 2), m).add_(1)
    rise = top - m
    if int(rise.max()) - 1 > brightest_level(contrast):
        return TooBright(rise > brightest_level(contrast) + 1)
    region = runs_of(counts, key.shape[0])
    bits = WORD_BITS - per_region.bit_length()
    # exp(c * j) * 2**bits rounds to 0 at j <= darkest + 1: levels below count as darkest.
    darkest = math.floor(-(bits + 2) * math.log(2) / contrast) - 1
    relative = [take(values, ids.view(-1)).view_as(ids).sub_(top[:, None]).clamp_(min=darkest)
                for values in (levels, new_levels)]
    if inside is not None:  # (ids outside the sensor read pixel 0)
        relative = [j.masked_fill_(~inside, 0) for j in relative]
    key = key - take((2 * top).to(key.dtype), region)
    lo = darkest
    if 2 - darkest > TABLE_SIZE:  # (a contrast below 6e-4) the levels the piece reaches
        lo = max(min(int(key.min()) // 2, min(int(j.min()) for j in relative)), darkest)
        if 2 - lo > TABLE_SIZE:
            return None
    # table[i]: the intensity at j = lo - 1 + i, up to j = 0.
    table = intensity_words(torch.arange(lo - 1, 1, device=key.device), contrast,
                   math.ldexp(1.0, bits), 1.0)[0]
    anchor, final = ((v if inside is None else v.masked_fill_(~inside, 0)).sum(1)
                     for v in (take(table, j.sub_(lo - 1).view(-1)).view_as(j)
                               for j in relative))
    # A region whose sum lies far below its brightest of the piece (it rose or fell by some
    # 200 levels at c = 0.2) holds too few bits to decide levels there: the two-word sums
    # take it (the caller's error bound would exceed NEAR_CAP anyway).
    if int(torch.minimum(anchor, final).min()) * threshold * NEAR_CAP < 2.02 * per_region:
        return None
    # Row i (j = lo + i): [change by OFF, change by ON], at 2 * (j - lo) + on.
    by_level = torch.stack([table[:-2] - table[1:-1], table[2:] - table[1:-1]], 1).reshape(-1)
    change = take(by_level, key.clamp_(min=2 * lo).sub_(2 * lo))
    total = telescoped_cumsum(change, firsts, anchor, final)
    smallest = int(total.min())
    # The smallest two-word sum, at least (each region's factor exp(c * (top - m)) / 2**bits
    # is above 2**-bits, and above its own smallest total): running_sums cuts before a sum
    # below its lowest, and then it must decide the piece; above it, its half a fine unit
    # per pixel is its error.
    scale, fine, lowest = two_word_scale(int((top - m).max()) - 1, per_region, contrast,
                                         threshold)
    factor = (top - m).to(torch.float64).mul_(contrast).exp_()
    least = math.ldexp(smallest, -bits) * float(factor.min())
    if not least >= lowest:  # each region's smallest total times its factor
        smallest_of = torch.full_like(top, torch.iinfo(torch.int64).max).scatter_reduce_(
            0, region, total, "amin")
        least = math.ldexp(float((smallest_of.to(torch.float64) * factor).min()), -bits)
    least *= 1 - per_region / max(smallest, 1) - 16 * EPS
    if not least >= lowest:
        return None
    return OneWordSums(region, top, total, bits, smallest, per_region / (2 * fine * scale) / least)


def one_word_moves(
    key: Tensor, ids: Tensor, inside: Tensor | None, levels: Tensor, new_levels: Tensor,
    firsts: Tensor, first: Tensor, log_pixels: Tensor | float, per_region: int,
    contrast: float, threshold: float,
) -> tuple[Tensor, Tensor, Tensor] | TooBright | None:
    """:func:`moves_to_solve` of a piece from its one-word sums (:func:`one_word_sums`).

    Every event whose ``u`` lies farther than the one-word sums' error bound from both snap
    bounds of its level (``k - SNAP`` and ``k + SNAP``) gets the ``floor(u)`` and on-level
    flag that the two-word sums (:func:`.sums.running_sums`) give; ``None`` where an event
    lies within it (or the one-word sums cannot be used): the caller then takes the two-word
    sums; :class:`TooBright` where some regions rise too far for one word. The bound is
    about ``1e-15`` in ``u`` where a region's sum is near its brightest intensity of the
    piece, so on ordinary streams that never happens.
    """
    n = key.shape[0]
    counts = torch.diff(firsts, append=firsts.new_tensor([n]))
    sums = one_word_sums(key, ids, inside, levels, new_levels, firsts, counts, per_region,
                         contrast, threshold)
    if sums is None or isinstance(sums, TooBright):
        return sums
    # u = (c * m - log(n_r) + log(sum)) / theta with sum = total * exp(c * (top - m)) / 2**bits,
    # within `margin` of the two-word path's u: twice the bound of the sums' relative error
    # over theta and of a few ulps of every term.
    offset = sums.top.to(torch.float64).mul_(contrast).sub_(log_pixels)
    offset.sub_(sums.bits * math.log(2)).div_(threshold)
    largest = float(offset.abs().max()) + (64 * math.log(2) + 1) / threshold

    def margin(smallest: Tensor | float) -> Tensor | float:
        relative = per_region / smallest + sums.two_word_error + 16 * EPS
        return 2 * (1.01 * relative / threshold + 8 * EPS * largest)

    widest = float(margin(float(sums.smallest)))
    if widest > NEAR_CAP:
        return None
    # w = u + SNAP + widest: a w less than 2 * (SNAP + widest) above its floor is near a
    # level; any other has floor(w) = floor(u) and is off every level, certainly.
    shift = SNAP + widest
    log_total = sums.total.to(torch.float64)
    # NumPy's logarithm: about 3.7x torch's on the CPU (262k values), within an ulp of it;
    # the margin covers a few ulps of every term.
    if log_total.device.type == "cpu":
        np.log(log_total.numpy(), out=log_total.numpy())
    else:
        log_total.log_()
    w = take(offset.add_(shift), sums.region).add_(log_total, alpha=1 / threshold)
    floor_w = torch.floor(w, out=log_total)
    frac = w.sub_(floor_w)
    near = frac <= 2 * shift
    kept, floor_w, near = moves_to_solve(floor_w, near, first)
    u = floor_w.add_(take(frac, kept)).sub_(shift)
    distance = torch.round(u).sub_(u).abs_().sub_(SNAP).abs_()
    doubt = where_true(distance <= widest)  # (each event's own bound is at most widest)
    if doubt.shape[0] and bool((take(distance, doubt) <= margin(
            take(take(sums.total, kept), doubt).to(torch.float64))).any()):
        return None  # an event within the error bound of a snap bound
    floor_u, on_level = snap(u)
    return kept, floor_u, on_level
