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
]


class Resume(NamedTuple):
    """Where a streaming window of the stream picks up (a bounded-delay session's state).

    The window holds, for each of its pixels, the knots it had before ``cut`` that the curves
    after ``cut`` still need (the last one, or the last two for PCHIP slopes) and every knot
    since. Each region resumes at its last breakpoint earlier than ``cut`` with the reference
    index it had there; the pieces before are not solved (the window's curves are not the
    stream's there).

    Attributes:
        cut: ``()`` time, or ``None`` for a window that starts at ``t_start`` (from ``q = 0``).
        q: ``(Wo * Ho,)`` int64 reference index of every output region after its last
            breakpoint earlier than ``cut`` (0 for a region without one).
    """

    cut: Tensor | None
    q: Tensor


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
    n_done = torch.zeros_like(knots.regions).index_add_(0, bp_rank, done.to(torch.int64))
    cut_bp = knots.region_first_bp + n_done - 1
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
