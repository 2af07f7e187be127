"""What a curve's solver takes and returns, and where a streaming window resumes.

The driver (:mod:`.driver`) hands each chunk of regions' :class:`~.knots.Knots` and a
:class:`RegionJob` to the curve's solver (:func:`.linear.linear_regions` or
:func:`.cubic.cubic_regions`), which returns its :class:`CurveCrossings`; in a bounded-delay
session (:mod:`.stream`) the job carries a :class:`Resume`, which :func:`resume_moves` applies.
Both solvers start from :func:`breakpoint_levels`, the exact part of the regions' curves.
"""

from __future__ import annotations

from collections.abc import Callable
from fractions import Fraction
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import run_index, segmented_cumsum, take, where_true
from evdown_torch.transforms.functional.estimation.knots import Knots, level_changes

__all__ = [
    "CurveCrossings",
    "RegionJob",
    "RegionSolver",
    "Resume",
    "breakpoint_levels",
    "resume_moves",
    "resumed_crossings",
]


class Resume(NamedTuple):
    """Where a streaming window of the stream picks up (a bounded-delay session's state).

    The window holds, for each of its pixels, the knots it had before ``cut`` that the curves
    after ``cut`` still need (the last one, or the last two for PCHIP slopes) and every knot
    since. Each region resumes at its last breakpoint earlier than ``cut`` with the reference
    index it had there; the pieces before are not solved (the window's curves are not the
    stream's there). The first ``returned`` crossings of the piece that crosses ``cut``
    were returned by the windows before (``resumed_crossings``, below).

    Attributes:
        cut: ``()`` time, or ``None`` for a window that starts at ``t_start`` (from ``q = 0``).
        q: ``(Wo * Ho,)`` int64 reference index of every output region after its last
            breakpoint earlier than ``cut`` (0 for a region without one).
        returned: ``(Wo * Ho,)`` int64 count of every region's crossings after that
            breakpoint returned already (0 for a region without one).
    """

    cut: Tensor | None
    q: Tensor
    returned: Tensor


def resume_moves(
    knots: Knots,
    move_bp: Tensor | None,
    floor_u: Tensor,
    on_level: Tensor,
    resume: Resume | None,
    bp_rank: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The moves of a window as the reference rule must see them, and each move's ``q_start``.

    Steps whose piece ends at a breakpoint earlier than ``resume.cut`` take the value of
    their region's last such move (the cut), so that they cross nothing: the region starts
    there from ``resume.q``, which is consistent with that value.

    Args:
        knots: the window's :class:`Knots` (one chunk of regions).
        move_bp: ``(S,)`` int64 breakpoint at the end of each move's piece, ascending, or
            ``None`` for one move per breakpoint (move ``i`` ends at breakpoint ``i``).
        floor_u: ``(S,)`` int64 ``floor(M / theta)`` at the end of each move.
        on_level: ``(S,)`` bool, the move ends on a level.
        resume: where the window picks up, or ``None`` (the whole stream from ``q = 0``).
        bp_rank: ``(B,)`` int64 rank of each breakpoint's region among ``knots.regions``,
            when the caller has it.

    Returns:
        ``(floor_u, on_level, q_start)`` for
        ``reference.move_crossings``.
    """
    if resume is None:
        return floor_u, on_level, None
    if bp_rank is None:
        bp_rank = run_index(knots.bp_first)
    move_rank = bp_rank if move_bp is None else take(bp_rank, move_bp)
    q_start = take(take(resume.q, knots.regions), move_rank)
    if resume.cut is None:
        return floor_u, on_level, q_start
    done = knots.bp_t < resume.cut  # a prefix of each region's breakpoints
    cut_bp = knots.region_first_bp + breakpoints_before(knots, bp_rank, resume.cut) - 1
    if move_bp is None:
        cut_move, at = cut_bp, where_true(done)
    else:
        cut_move = torch.searchsorted(move_bp, cut_bp, right=True) - 1
        at = where_true(take(done, move_bp))
    source = take(cut_move, take(move_rank, at))
    floor_u, on_level = floor_u.clone(), on_level.clone()
    floor_u[at] = take(floor_u, source)
    on_level[at] = take(on_level, source)
    return floor_u, on_level, q_start


def breakpoints_before(knots: Knots, bp_rank: Tensor, time: Tensor) -> Tensor:
    """``(R,)`` int64 count of each region's breakpoints earlier than ``time`` (a prefix).

    ``bp_rank``: ``(B,)`` rank of each breakpoint's region among ``knots.regions``.
    """
    before = (knots.bp_t < time).to(torch.int64)
    return torch.zeros_like(knots.regions).index_add_(0, bp_rank, before)


def breakpoint_levels(knots: Knots, bp_first_at: Tensor, region: Tensor) -> Tensor:
    """``(B,)`` int64 exact integer part of ``n_r * M_r`` at every breakpoint.

    The sum of the levels of the latest knots of the region's pixels: each knot's level change
    (:func:`~.knots.level_changes`) added at its breakpoint, summed along the region's
    breakpoints. What the curves add between knots (the pixels strictly inside a segment) is
    each solver's own.

    Args:
        knots: one chunk of regions' :class:`Knots`.
        bp_first_at: ``(R,)`` int64 first breakpoint of each region (``where_true`` of
            ``knots.bp_first``).
        region: ``(B,)`` int64 rank of each breakpoint's region in the chunk
            (``run_index`` of ``knots.bp_first``).
    """
    changes = torch.zeros(knots.bp_t.shape[0], dtype=torch.int64, device=knots.t.device)
    changes.index_add_(0, knots.breakpoint, level_changes(knots))
    return segmented_cumsum(changes, bp_first_at, region)


class RegionJob(NamedTuple):
    """What a curve's solver needs besides the knots of one chunk of regions.

    Attributes:
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        fraction: the threshold as the rational ``a / b`` of ``threshold_fraction``.
        emitted: events of the chunks before (for the output limit).
        resume: where a streaming window starts
            (:func:`resume_moves`), or
            ``None``.
        front_at_rest: a bounded delay: pixels at rest before their first knot (the cubic
            slope there is 0; nothing changes for polylines).
    """

    sensor_size: tuple[int, int, int]
    factor: tuple[int, int]
    fraction: Fraction
    emitted: int = 0
    resume: Resume | None = None
    front_at_rest: bool = False


class CurveCrossings(NamedTuple):
    """The crossings a solver finds, in region order.

    Attributes:
        region: ``(C,)`` int64 output region of every crossing.
        t: ``(C,)`` crossing times (the events' dtype).
        on: ``(C,)`` bool, an ON crossing.
        breakpoint: ``(C,)`` int64 breakpoint that ends each crossing's piece.
    """

    region: Tensor
    t: Tensor
    on: Tensor
    breakpoint: Tensor


#: A curve's solver: the crossings of the regions of one chunk of knots.
RegionSolver = Callable[[Knots, RegionJob], CurveCrossings]


def resumed_crossings(
    knots: Knots, found: CurveCrossings, resume: Resume, next_cut: Tensor | None,
    returned: Tensor,
) -> tuple[Tensor, Tensor]:
    """The crossings of a resumed window that it returns, and their times.

    A window recomputes the piece of each region that crosses its ``cut`` (from the region's
    last breakpoint earlier than ``cut``), from other knots than the window before: a float
    time may round to the other side of ``cut``. So the window before counts the crossings
    of that piece it returned (``resume.returned``), and this one drops as many, by their
    order along the piece, not by their times; the others come out no earlier than ``cut``
    (a time rounded below it is raised to it, so the output stays in time order). The
    crossings of the pieces that end before ``cut`` were returned before.

    With ``next_cut`` (a session's step), a region's crossings are returned in their order
    up to the first at or after ``next_cut``, and ``returned`` is set, for the window's
    regions, to the count of those returned of the piece that crosses ``next_cut``
    (``resume.returned``'s too, where the piece is the same). Without (the flush), all.

    Args:
        knots: the window's :class:`Knots` (one chunk of regions).
        found: the solver's crossings of these knots, in region order (``(C,)``).
        resume: where the window picks up.
        next_cut: ``()`` the next window's cut, or ``None``.
        returned: ``(Wo * Ho,)`` int64, written in place at the window's regions (with
            ``next_cut``).

    Returns:
        ``(index, t)``: ``(C',)`` int64 index of the crossings returned, ascending, and their
        ``(C',)`` times.
    """
    device = found.t.device
    n_regions = knots.regions.shape[0]
    bp_rank = run_index(knots.bp_first)
    rank = take(bp_rank, found.breakpoint)  # (C,) each crossing's region, ranked
    position = torch.arange(rank.shape[0], device=device)
    position -= torch.searchsorted(rank, rank)  # its order in its region
    end = found.breakpoint - take(knots.region_first_bp, rank)  # its piece's end, in region
    zeros = torch.zeros(n_regions, dtype=torch.int64, device=device)
    n_cut = zeros if resume.cut is None else breakpoints_before(knots, bp_rank, resume.cut)
    old = take(resume.returned, knots.regions).masked_fill_(n_cut == 0, 0)
    cut_of = take(n_cut, rank)
    before = end < cut_of  # a piece that ends before the cut
    crossing = (cut_of > 0) & (end == cut_of)  # the piece that crosses the cut
    n_before = zeros.clone().index_add_(0, rank, before.to(torch.int64))
    keep = ~before & ~(crossing & (position - take(n_before, rank) < take(old, rank)))
    t = found.t
    if resume.cut is not None:
        t = torch.where(crossing, torch.maximum(t, resume.cut), t)
    if next_cut is not None:
        late = where_true(keep & (t >= next_cut))
        stop = torch.full((n_regions,), rank.shape[0], dtype=torch.int64, device=device)
        stop.scatter_reduce_(0, take(rank, late), take(position, late), "amin")
        keep &= position < take(stop, rank)
        n_next = breakpoints_before(knots, bp_rank, next_cut)
        next_of = take(n_next, rank)
        counted = keep & (next_of > 0) & (end == next_of)
        count = zeros.clone().index_add_(0, rank, counted.to(torch.int64))
        count += old.masked_fill_((n_next == 0) | (n_next != n_cut), 0)
        returned[knots.regions] = count
    index = where_true(keep)
    return index, take(t, index)
