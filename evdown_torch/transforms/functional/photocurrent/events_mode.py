"""Photocurrent pooling kernels (docs/semantics.md, method 7): events to video to events.

Each input pixel keeps an integer level ``L_p`` (ON +1, OFF -1) and its log intensity is
``c * L_p``. A region's photocurrent is the mean of its pixels' intensities,
``I_r = (1 / n_r) * sum exp(c * L_p)``, and the output pixel runs the DVS reference rule on
``log I_r`` at contrast ``theta``: with ``u = log(I_r) / theta``, the shared rule of
:mod:`~evdown_torch.transforms.functional.reference` (floor of ``u`` and whether ``u`` is on a
level, a ``u`` within :data:`.knots.SNAP` of an integer
counting as on it).

*Events mode* (:func:`photocurrent_events`): ``log I_r`` changes only at input events. The
stream goes in pieces (about 16 events per pixel, at most :data:`CHUNK_EVENTS`). In a piece,
one sort groups the events by region (time order inside); each region's photocurrent after
each of its events comes from exact int64 fixed-point running sums anchored at its brightest
pixel (:mod:`~evdown_torch.transforms.functional.photocurrent.sums`), to a few ulps however
many events the piece has; a region whose pixels climb more than
:data:`~evdown_torch.transforms.functional.photocurrent.sums.MAX_EXPONENT` above its anchor
takes a new anchor each time they do (:func:`.sums.rising_anchors`). Where the sums cannot
hold an event to ``1e-10 * theta`` (all of a region's pixels falling some 50 log units below
its anchor), that region's events from there on are held back, and decided after the others'
on a piece that re-anchors that region where it was cut (regions are independent), or once
few are left from a row of its region's levels after each event; a piece that would decide
nothing decides its first event alone that way. The reference rule then runs on the events
that can change a region's reference index.

A long piece is first tried with one int64 word per sum (:func:`.one_word.one_word_sums`), which
decides every event clear of the snap bounds by more than its error bound as the two words
would; a piece with an event within it goes to them. Regions that climb too far for one word
are held back, and their events follow on the two-word sums.

*Frames mode*: :mod:`~evdown_torch.transforms.functional.photocurrent.frames_mode`; what both
modes share (pixel levels, region geometry, level snap) is in
:mod:`~evdown_torch.transforms.functional.photocurrent.levels`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._regions import pixel_columns, region_pixel_count, region_xy
from evdown_torch._tensors import (
    CHUNK_EVENTS,
    divide,
    ends,
    last_of_runs,
    run_index,
    stable_sort_small,
    take,
    where_true,
)
from evdown_torch.checks import check_state_memory, output_size
from evdown_torch.events import Events, polarity_sign, sort_by_time
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.photocurrent.levels import (
    check_contrast_range,
    check_level_range,
    log_mean_exp,
    region_levels_after,
    region_pixel_ids,
    snap,
)
from evdown_torch.transforms.functional.photocurrent.one_word import TooBright, one_word_moves
from evdown_torch.transforms.functional.photocurrent.settings import PhotocurrentState
from evdown_torch.transforms.functional.photocurrent.sums import grouped_levels, running_sums
from evdown_torch.transforms.functional.reference import (
    moves_to_solve,
    region_dtype,
    region_runs,
    rule_crossings,
)

#: Fewest events of a piece that the one-word sums (:func:`.one_word.one_word_moves`) decide: below,
#: their few fixed costs (a table of every level that counts, and their checks) outweigh
#: their lower cost per event, and the two-word sums decide.
ONE_WORD_MIN_EVENTS = 1 << 14

#: Most level values (events x ``fx * fy``) of held-back events that :func:`_anchored_piece`
#: decides in one dense round (a row of its region's levels per event, no anchor, nothing
#: held back again) rather than on the two-word sums: 8 MB of int64 levels.
DENSE_VALUES = 1 << 18


def initial_state(
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    device: torch.device | str | None = None,
    recordings: int = 1,
) -> PhotocurrentState:
    """A fresh state: every pixel at level 0 (intensity 1), every region with ``q = 0``.

    With ``recordings > 1``, the state of that many recordings stacked vertically (recording
    ``b``'s pixel ``(x, y)`` at ``(x, y + b * Ho * fy)``, see
    ``transforms.functional.batch``).
    """
    w, h, _ = sensor_size
    out_w, out_h, _ = output_size(sensor_size, factor)
    check_state_memory("PhotocurrentPooling", sensor_size, factor, pixel_bytes=8,
                       region_bytes=8, recordings=recordings, device=device)  # int64 each
    rows = h if recordings == 1 else out_h * factor[1] * recordings
    return PhotocurrentState(
        torch.zeros(w * rows, dtype=torch.int64, device=device),
        torch.zeros(out_w * out_h * recordings, dtype=torch.int64, device=device),
        None,
    )


class _Regions(NamedTuple):
    """The events of some whole regions of a piece, grouped by region (time order inside)."""

    order: Tensor  # (n,) int64 position of each event in the piece
    region: Tensor  # (n,) region id of each event
    first: Tensor  # (n,) bool, the region's first event
    key: Tensor  # (n,) 2 * L + on (L: its pixel's level before it)
    touched: Tensor  # (S,) their region ids, ascending
    ids: Tensor  # (S, fx * fy) int64 their pixel ids (region_pixel_ids)
    inside: Tensor | None  # (S, fx * fy) bool, the pixel is on the sensor (None: all are)


def _two_word_u(
    events: Events, part: _Regions, levels: Tensor, sensor_size: tuple[int, int, int],
    factor: tuple[int, int], contrast: float, threshold: float,
    runs: tuple[Tensor, Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor | None]:
    """``u = log(I_r) / theta`` after each event of ``part`` from the two-word running sums.

    ``runs``: each region's first and last event and each event's region (rank), when the
    caller has them. Returns ``(u, bad)``: ``bad`` as :attr:`.sums.RunningSums.bad`
    (``part.key`` is overwritten).
    """
    if runs is None:
        firsts = where_true(part.first)
        runs = (firsts, last_of_runs(firsts, part.first.shape[0]),
                run_index(part.first))
    firsts, lasts, rank = runs

    def slot() -> Tensor:  # each event's column in ids, for regions that climb
        return pixel_columns(events.select(part.order), factor)

    sums = running_sums(part.key, part.ids, part.inside, levels, firsts, lasts, rank,
                        factor[0] * factor[1], contrast, threshold, slot)
    anchored = part.touched if sums.anchor_region is None else take(part.touched,
                                                                    sums.anchor_region)
    log_pixels = region_pixel_count(anchored, sensor_size, factor).to(torch.float64).log_()
    offset = sums.anchor.to(torch.float64).mul_(contrast).sub_(log_pixels).div_(threshold)
    return take(offset, sums.anchor_of).add_(sums.total.log_(), alpha=1 / threshold), sums.bad


def _two_word_moves(
    events: Events, part: _Regions, levels: Tensor, sensor_size: tuple[int, int, int],
    factor: tuple[int, int], contrast: float, threshold: float,
) -> tuple[Tensor, Tensor, Tensor] | None:
    """The moves to solve (``moves_to_solve``) of ``part``; ``None`` where its sums cut."""
    u, bad = _two_word_u(events, part, levels, sensor_size, factor, contrast, threshold)
    if bad is not None:
        return None
    floor_u, on_level = snap(u)
    return moves_to_solve(floor_u, on_level, part.first)


# --------------------------------------------------------------------------------------------
# Events mode


def photocurrent_events(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    contrast: float,
    threshold: float,
) -> Events:
    """Photocurrent pooling, events mode (docs/semantics.md, method 7): causal, streamable.

    After each input event, in stable time order, its region's ``u = log(I_r) / threshold``
    with ``I_r = mean(exp(contrast * L_p))`` is tested with the DVS reference rule; emitted
    events take the triggering event's ``t``.

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        contrast: ``c``, the input camera's contrast threshold in log units, in [1e-6, 50].
        threshold: ``theta``, the output pixel's contrast threshold in log units.

    Returns:
        Output events sorted by ``t`` (a stream in chunks goes through
        :func:`photocurrent_sorted`, a session's step).

    Example:
        Two ON events in a 2x1 region at contrast ln 2: the photocurrent goes 1 -> 1.5 -> 2,
        so only the second event reaches the level ``ln 2``.

        >>> import math
        >>> ev = Events.from_columns([0, 1], [0, 0], [5, 9], [1, 1])
        >>> out = photocurrent_events(ev, sensor_size=(2, 1, 2), factor=(2, 1),
        ...                           contrast=math.log(2), threshold=math.log(2))
        >>> out.t.tolist(), out.p.tolist()
        ([9], [True])
    """
    out, _ = photocurrent_sorted(sort_by_time(events), sensor_size, factor, contrast, threshold,
                                 None)
    return out


def photocurrent_sorted(
    events: Events, sensor_size: tuple[int, int, int], factor: tuple[int, int], contrast: float,
    threshold: float, state: PhotocurrentState | None, recordings: int = 1,
) -> tuple[Events, PhotocurrentState]:
    """:func:`photocurrent_events` of events already in stable time order (a session's chunk).

    ``state``: the state after the previous chunk of the stream (``None``: a fresh stream);
    ``recordings``: ``B``, for a batch of recordings stacked vertically (recording ``b``'s
    pixel ``(x, y)`` given as ``(x, y + b * Ho * fy)``, see
    ``transforms.functional.batch``). Returns ``(output, state)``.

    On the CPU the compiled loop of ``transforms.functional.compiled.photocurrent`` (the same
    events and state) decides the call, unless the eager kernels are forced
    (:func:`~evdown_torch.eager_kernels`, ``EVDOWN_EAGER``) or the loop leaves the call to
    this kernel (an event too near a snap bound, an output past the limit).
    """
    check_contrast_range(contrast, threshold)
    if state is None:
        state = initial_state(sensor_size, factor, events.device, recordings)
    n = events.num_events
    if n == 0:
        return Events.empty(events.t.dtype, events.device), state
    # No level of the call exceeds level_bound: the largest level so far plus one per event,
    # read from the events' pixels when they are fewer than the sensor's (untouched pixels
    # keep levels checked when they were last touched).
    if n < state.level.shape[0]:
        level_bound = int(take(state.level, events.y * sensor_size[0] + events.x).abs().max())
    else:
        level_bound = int(state.level.abs().max())
    level_bound += n
    check_level_range(level_bound, contrast, threshold)
    if use_compiled(events.t):  # the compiled loop, unless it leaves the call to this kernel
        from evdown_torch.transforms.functional.compiled import photocurrent as compiled

        result = compiled.photocurrent_step(events, sensor_size, factor, contrast, threshold,
                                            state)
        if result is not None:
            return result
    outputs = []
    # Pieces of about 16 events per pixel: re-anchoring then costs little (at most the
    # sensor's pixels per piece) and a small sensor's pieces stay in the CPU's caches.
    size = min(max(16 * sensor_size[0] * sensor_size[1], 1 << 16), CHUNK_EVENTS)
    emitted = 0
    for start in range(0, n, size):
        piece = events.part(start, min(start + size, n))
        out, state = _anchored_piece(piece, sensor_size, factor, contrast, threshold, state,
                                     emitted, level_bound)
        outputs.append(out)
        emitted += out.num_events
    return Events.cat(outputs), state


class PieceResult(NamedTuple):
    """What :func:`_events_piece` decided of a time-sorted piece.

    Attributes:
        out: output events, in time order.
        source: ``(M,)`` int64 position in the piece of the event behind each output event,
            ascending.
        state: the state after the events decided.
        rest: ``None``, or the ``(R,)`` int64 positions (ascending) of the events not decided:
            those of the regions whose running sums could not hold them, from the first such
            event of each region on. They follow the decided ones on a piece re-anchored at
            ``state``.
    """

    out: Events
    source: Tensor
    state: PhotocurrentState
    rest: Tensor | None


def _anchored_piece(
    events: Events, sensor_size: tuple[int, int, int], factor: tuple[int, int],
    contrast: float, threshold: float, state: PhotocurrentState, emitted: int,
    level_bound: int,
) -> tuple[Events, PhotocurrentState]:
    """:func:`_events_piece`, then again on the events it held back, until none are left.

    Regions are independent, so the held-back events of a region (a pixel rising too far
    above its anchor for one word, or a fall too deep for the two words) go on from that
    region's state at its cut while every other region's events are decided in one go; the
    outputs are merged back in the order of the events behind them. A round takes the
    two-word sums, whose anchors climb with the regions, re-anchored where each region was
    cut; once few events are left (:data:`DENSE_VALUES`) one dense round decides them all.
    """
    result = _events_piece(events, sensor_size, factor, contrast, threshold, state, emitted,
                           level_bound)
    if result.rest is None:
        return result.out, result.state
    outputs, sources = [result.out], [result.source]
    rest: Tensor | None = result.rest
    state = result.state
    while rest is not None:
        emitted += outputs[-1].num_events
        dense = rest.shape[0] * factor[0] * factor[1] <= DENSE_VALUES
        again = _events_piece(events.select(rest), sensor_size, factor, contrast, threshold,
                              state, emitted, level_bound, dense, one_word=False)
        outputs.append(again.out)
        sources.append(take(rest, again.source))
        state = again.state
        rest = None if again.rest is None else take(rest, again.rest)
    by_source = torch.sort(torch.cat(sources), stable=True).indices
    return Events.cat(outputs).select(by_source), state._replace(last_t=events.t[-1].clone())


def _events_piece(
    events: Events,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    contrast: float,
    threshold: float,
    state: PhotocurrentState,
    emitted: int = 0,
    level_bound: int = 2**62,
    dense: bool = False,
    one_word: bool = True,
) -> PieceResult:
    """Events mode on one time-sorted piece anchored at ``state``.

    ``emitted`` counts the events of earlier pieces, for the output cap of
    :func:`~evdown_torch.checks.check_output_count`; ``level_bound`` bounds every pixel level
    before and after the piece (int32 arithmetic where it allows). Where the running sums
    cannot hold an event of a region to the required accuracy, that region's events from
    there on are held back (:attr:`PieceResult.rest`): the output and state are those of the
    events before; the caller re-anchors the held-back regions there. ``dense``: every
    event's sum from a row of its region's levels after it (:func:`.levels.region_levels_after`;
    ``fx * fy`` values an event, no anchor: nothing is held back), as a lone event's always.
    ``one_word=False``: the two-word sums at once (held-back regions, which rose too far for
    one word).
    """
    w = sensor_size[0]
    fx, fy = factor
    out_w = output_size(sensor_size, factor)[0]
    per_region = fx * fy
    n = events.num_events
    regions = state.reference.shape[0]
    # Region coordinates and ids in the narrowest integer type that holds them and the
    # sensor's coordinates (as EventCount's kernel does).
    narrow = region_dtype(sensor_size, factor, regions)
    x, y = events.x.to(narrow, copy=True), events.y.to(narrow, copy=True)
    rx, ry = divide(x, fx), divide(y, fy)
    # Pixel and polarity packed as 2 * (y * W + x) + on, in int32 where every level fits too.
    wide = torch.int32 if 2 * state.level.shape[0] < 2**31 and level_bound < 2**28 else (
        torch.int64)
    pixel_on = y.to(wide, copy=True).mul_(w).add_(x).mul_(2).add_(events.p)
    place, bound = None, 1
    if per_region > 1:  # the pixel's place in its region, and a few high bits of the region
        chunks = max(1, 256 // per_region)
        bound = chunks * per_region
        shift = max(0, (regions - 1).bit_length() - (chunks.bit_length() - 1))
        place = y.sub_(ry, alpha=fy).mul_(fx).add_(x).sub_(rx, alpha=fx)
    del x, y
    ry.mul_(out_w).add_(rx)
    del rx
    # Region ids stay narrow after the sort; look-ups convert the few they need.
    region, order = stable_sort_small(ry, regions, narrow=True)
    if place is not None:
        place.add_(ry.bitwise_right_shift_(shift), alpha=per_region)
        place = take(place.to(torch.uint8) if bound <= 256 else place, order)
    del ry
    touched, firsts, lasts, first = region_runs(region, regions)
    key, new_levels = grouped_levels(take(pixel_on, order), place, bound, state.level)
    del place, pixel_on

    ids, inside = region_pixel_ids(touched, sensor_size, factor)

    def log_pixels() -> Tensor:
        return region_pixel_count(touched, sensor_size, factor).to(torch.float64).log_()

    moves: tuple[Tensor, Tensor, Tensor] | None = None
    rest: Tensor | None = None  # positions of the events held back, in any order
    log_n = math.log(per_region) if sensor_size[0] % fx == 0 and sensor_size[1] % fy == 0 else (
        None)  # (log(n_r) as one float where every region is whole)
    climbing: list[_Regions] = []  # regions that rose too far for one word
    while one_word and not dense and key.shape[0] >= ONE_WORD_MIN_EVENTS:
        tried = one_word_moves(key, ids, inside, state.level, new_levels, firsts, first,
                               log_pixels() if log_n is None else log_n, per_region,
                               contrast, threshold)
        if not isinstance(tried, TooBright):
            moves = tried
            break
        hot = tried.regions
        held = take(hot, run_index(first))
        if key.shape[0] - int(held.sum()) < ONE_WORD_MIN_EVENTS:
            break  # the two-word sums decide (and cut) them all
        # Try again without those regions, which the two-word sums decide after the others:
        # each region is independent of the others.
        at = where_true(held)
        climbing.append(_Regions(take(order, at), take(region, at), take(first, at),
                                 take(key, at), touched[hot], ids[hot],
                                 None if inside is None else inside[hot]))
        kept = where_true(~held)
        order, region, first, key = (take(v, kept) for v in (order, region, first, key))
        touched, ids = touched[~hot], ids[~hot]
        inside = None if inside is None else inside[~hot]
        firsts = where_true(first)
        lasts = last_of_runs(firsts, kept.shape[0])
    for part in climbing:
        decided = None if moves is None else _two_word_moves(
            events, part, state.level, sensor_size, factor, contrast, threshold)
        if moves is None or decided is None:
            # They wait for a piece re-anchored after them (_anchored_piece).
            rest = part.order if rest is None else torch.cat([rest, part.order])
            hot_ids = part.ids.view(-1) if part.inside is None else part.ids[part.inside]
            new_levels.index_copy_(0, hot_ids, take(state.level, hot_ids))
            continue
        # Decided here: their moves follow the others' (each region's stay together).
        moves = (torch.cat([moves[0], decided[0].add_(order.shape[0])]),
                 torch.cat([moves[1], decided[1]]), torch.cat([moves[2], decided[2]]))
        order, region, first = (torch.cat([order, part.order]), torch.cat([region, part.region]),
                                torch.cat([first, part.first]))
    if moves is None:
        rank = run_index(first)
        # u = log(I_r) / theta = (c * m + log(total / n_r)) / theta, then the reference rule.
        if dense or key.shape[0] == 1:  # each event's sum from its region's levels after it
            rows = region_levels_after(events.select(order), factor, rank, firsts,
                                       take(state.level, ids.view(-1)).view_as(ids))
            m, total = log_mean_exp(rows, None if inside is None else take(inside, rank),
                                    contrast)
            del rows, ids, inside, key
            offset = m.to(torch.float64).mul_(contrast).sub_(take(log_pixels(), rank))
            u = offset.div_(threshold).add_(total.log_(), alpha=1 / threshold)
        else:
            u, bad = _two_word_u(events, _Regions(order, region, first, key, touched, ids,
                                                  inside), state.level, sensor_size, factor,
                                 contrast, threshold, (firsts, lasts, rank))
            del ids, inside, key
            if bad is not None:  # the running sums cannot hold an event: its region waits
                # Each region keeps its events before the first that its sums cannot hold.
                bad_at = where_true(bad)
                cut = torch.full_like(firsts, n).scatter_reduce_(0, take(rank, bad_at), bad_at,
                                                                 "amin")
                keep = torch.arange(rank.shape[0], device=events.device) < take(cut, rank)
                if not bool(keep.any()):  # none: the piece's first event alone, then the rest
                    lone = _events_piece(events.part(0, 1), sensor_size, factor, contrast,
                                         threshold, state, emitted)
                    return lone._replace(rest=torch.arange(1, n, device=events.device))
                waiting = take(order, where_true(~keep))
                rest = waiting if rest is None else torch.cat([rest, waiting])
                kept = where_true(keep)
                order, region, first, u = (take(v, kept) for v in (order, region, first, u))
                new_levels = state.level.clone()
                new_levels.index_add_(0, take(events.y, order) * w + take(events.x, order),
                                      polarity_sign(take(events.p, order), torch.int64))
        floor_u, on_level = snap(u)
        del u
        # The reference rule on the moves that can change q only (a move that stays strictly
        # inside the cell its predecessor ended in keeps q and crosses nothing): a tenth or
        # less of the events when a level takes several events to cross.
        moves = moves_to_solve(floor_u, on_level, first)
    kept, floor_u, on_level = moves
    del moves
    region, first = take(region, kept), take(first, kept)
    # Every region's q before the piece (a 0-d zero while all are 0: no look-up).
    q_start = take(state.reference, region.long()) if bool(state.reference.any()) else (
        first.new_zeros((), dtype=torch.int64))
    cross, q = rule_crossings(floor_u, on_level, first, q_start, emitted=emitted)
    del q_start, floor_u, on_level

    # Back to time order: crossings of one move keep their level order.
    move_at = take(kept, cross.move)
    source, by_time = stable_sort_small(take(order, move_at), n)
    out_x, out_y = region_xy(take(region, take(cross.move, by_time)).long(), out_w)
    out = Events(out_x, out_y, take(events.t, source), take(cross.on, by_time))

    lasts = where_true(ends(first))
    new_reference = state.reference.clone()
    new_reference.scatter_(0, take(region, lasts).long(), take(q, lasts))
    state = PhotocurrentState(new_levels, new_reference, events.t[-1].clone())
    return PieceResult(out, source, state, None if rest is None else torch.sort(rest).values)
