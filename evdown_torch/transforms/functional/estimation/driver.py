"""The estimators' shared driver: the knots of each chunk of regions, then the curve's solver.

:func:`estimate` runs a whole stream (or a stacked batch of recordings) and
:func:`estimate_window` a window of one (a bounded-delay session's step,
:mod:`~evdown_torch.transforms.functional.estimation.stream`); both hand each chunk of
regions' :class:`~evdown_torch.transforms.functional.estimation.knots.Knots` to the curve's solver
(:func:`~evdown_torch.transforms.functional.estimation.linear.linear_regions` or
:func:`~evdown_torch.transforms.functional.estimation.cubic.cubic_regions`), which returns its
:class:`~.solver.CurveCrossings`.
"""

from __future__ import annotations

from types import ModuleType

import torch
from torch import Tensor

from evdown_torch._tensors import divide, take, where_true
from evdown_torch.events import Events, polarity_sign, sort_by_time
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.estimation.cubic import cubic_regions
from evdown_torch.transforms.functional.estimation.delay import hold_knots
from evdown_torch.transforms.functional.estimation.knots import (
    check_span,
    emit,
    pixel_knots,
    region_chunks,
)
from evdown_torch.transforms.functional.estimation.linear import linear_regions
from evdown_torch.transforms.functional.estimation.settings import Curve, EstimationSettings
from evdown_torch.transforms.functional.estimation.solver import (
    RegionJob,
    RegionSolver,
    Resume,
    resumed_crossings,
)
from evdown_torch.transforms.functional.reference import capped_threshold, threshold_fraction

__all__ = ["SOLVERS", "compiled_curve", "compiled_upkeep", "estimate", "estimate_window"]

#: The solver of each curve (``EstimationSettings.curve``): the one table of them.
SOLVERS: dict[Curve, RegionSolver] = {"linear": linear_regions, "cubic": cubic_regions}

#: Events per chunk of regions in :func:`estimate_window`. The kernels keep a few dozen
#: temporaries of a chunk's size alive at once; at 2**17 events (about 1 MB each) the
#: allocator recycles them from chunk to chunk instead of faulting fresh pages in, which made
#: the 1M-event gesture stream about 1.3x (linear) and 1.2x (cubic) faster than chunks of
#: 2**20 on the CPU (docs/benchmarks.md, "Estimators"). A region's result does not depend on
#: the regions solved with it, so the chunk size changes no output.
REGION_CHUNK_EVENTS = 1 << 17


def estimate(
    events: Events,
    settings: EstimationSettings,
    *,
    recording_spans: tuple[Tensor, Tensor] | None = None,
) -> Events:
    """The batch entry of the estimation kernels: the whole stream, then :func:`estimate_window`.

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        settings: the estimator's settings; the solver of its ``curve`` (:data:`SOLVERS`)
            returns the :class:`~.solver.CurveCrossings` of the regions of one chunk, in
            region order. With ``max_delay`` (:func:`hold_knots`) the pixels hold their level
            until ``D`` before each knot; ``None`` is the paper's method.
        recording_spans: for a batch of ``B`` recordings stacked vertically (recording ``b``'s pixel
            ``(x, y)`` given as ``(x, y + b * Ho * fy)``, see
            :mod:`evdown_torch.transforms.functional.batch`), the ``(B,)`` first and last timestamps
            of each recording, its ``t_start`` and ``t_end``; ``None`` for one stream.

    Returns:
        Output events sorted by ``t``, ``t`` of the input's dtype.

    Raises:
        ValueError: for integer timestamps spanning 2**53 or more
            (:func:`~evdown_torch.checks.check_time_span`), or an output above
            :func:`~evdown_torch.checks.max_output_events`.
    """
    events = sort_by_time(events)
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device)
    t_start, t_end = events.t[0], events.t[-1]
    if recording_spans is not None:
        t_start, t_end = recording_spans
    check_span(t_start, t_end)  # before any time arithmetic
    change = None
    if settings.max_delay is not None:
        start = t_start
        if recording_spans is not None:  # each event's own recording's t_start
            rows = settings.output_sensor_size[1] * settings.factor[1]
            start = take(t_start, divide(events.y, rows))
        compiled = compiled_upkeep(events.t)
        upkeep = None if compiled is None else (compiled.held_knots, compiled.merge_by_time)
        events, change = hold_knots(events, max_delay=settings.max_delay, t_start=start,
                                    upkeep=upkeep)
    out, _ = estimate_window(events, change=change, t_start=t_start, t_end=t_end, settings=settings,
                             front_at_rest=settings.max_delay is not None)
    return out


def estimate_window(
    events: Events,
    *,
    change: Tensor | None,
    t_start: Tensor,
    t_end: Tensor,
    settings: EstimationSettings,
    resume: Resume | None = None,
    next_cut: Tensor | None = None,
    front_at_rest: bool = True,
) -> tuple[Events, Resume | None]:
    """The driver the estimation kernels share: knots of each chunk of regions, then output.

    Batch (:func:`estimate`): the whole stream, or a batch of stacked recordings. Streaming
    (a bounded-delay session): a window of one stream, the knot events its pixels still
    need, resumed at ``resume``.

    Args:
        events: ``N >= 1`` knot events in stable time order, within ``[t_start, t_end]``.
        change: ``(N,)`` int8 or int64 level change of each event (``None``: +1 ON, -1 OFF).
        t_start: ``()`` first timestamp of the stream (its front knots), or ``(B,)`` those of
            a batch of stacked recordings (see :func:`estimate`).
        t_end: ``()`` last timestamp of the stream so far (the back knots), or ``(B,)``.
        settings: as for :func:`estimate` (its ``max_delay`` is not read here).
        resume: where a window picks up
            (:class:`~.solver.Resume`), or
            ``None`` (from ``t_start``).
        next_cut: with ``resume``, the next window's cut: only the crossings before it are
            returned (:func:`~.solver.resumed_crossings`), and the next window's
            :class:`~.solver.Resume` at it.
        front_at_rest: a bounded delay (always so in a streaming window): the pixels are at
            rest before their first knot (docs/semantics.md, "Bounded delay"; the cubic
            slope there is 0).

    Returns:
        ``(events, resume)``: output events sorted by ``t`` (``t`` of the input's dtype; with
        ``resume``, only those not returned before it, :func:`~.solver.resumed_crossings`),
        and with ``resume`` and ``next_cut`` the next window's :class:`~.solver.Resume`
        (``None`` without).
    """
    n = events.num_events
    # Every curve stays within its knots' levels, at most sum |change| in size (PCHIP is
    # shape-preserving; a window's first knot of a pixel carries its whole level).
    bound = n if change is None else int(change.abs().sum())
    sensor_size, factor, solver = settings.sensor_size, settings.factor, SOLVERS[settings.curve]
    fraction = capped_threshold(threshold_fraction(settings.threshold), bound)
    out_w, out_h, _ = settings.output_sensor_size
    if use_compiled(events.t) and compiled_curve(settings.curve):
        from evdown_torch.transforms.functional.compiled.estimation import estimation_window

        found = estimation_window(
            events.x, events.y, events.t, polarity_sign(events.p) if change is None else change,
            t_start=t_start, t_end=t_end, sensor_size=sensor_size, factor=factor,
            out_size=(out_w, out_h), fraction=fraction,
            resume_cut=None if resume is None else resume.cut,
            resume_q=None if resume is None else resume.q,
            resume_returned=None if resume is None else resume.returned, next_cut=next_cut,
            chunk_events=REGION_CHUNK_EVENTS, cubic=settings.curve == "cubic",
            front_at_rest=front_at_rest,
        )
        if found is not None:  # else a level change too wide for the loop: the eager path
            region, t, on, q, returned = found
            after = None if q is None or returned is None else Resume(next_cut, q, returned)
            return emit(region, t, on, out_w), after
    q = None if resume is None else resume.q.clone()
    returned = None if resume is None else resume.returned.clone()
    outputs = []
    emitted = 0
    for chunk in region_chunks(events, factor=factor, out_width=out_w, change=change,
                               size=REGION_CHUNK_EVENTS):
        start, end = t_start, t_end
        if t_start.ndim:  # each event's own recording's bounds
            recording = divide(chunk.region, out_w * out_h)
            start, end = take(t_start, recording), take(t_end, recording)
        knots = pixel_knots(chunk, factor=factor, t_start=start, t_end=end)
        job = RegionJob(sensor_size, factor, fraction, emitted, resume, front_at_rest)
        crossings = solver(knots, job)
        region, t, on, bp = crossings
        emitted += region.shape[0]
        if q is not None and next_cut is not None:
            decided = where_true(take(knots.bp_t, bp) < next_cut)
            sign = polarity_sign(take(on, decided), torch.int64)
            q.index_add_(0, take(region, decided), sign)
        if resume is not None and returned is not None:
            index, t = resumed_crossings(knots, crossings, resume, next_cut, returned)
            region, on = take(region, index), take(on, index)
        outputs.append((region, t, on))
    region, t, on = outputs[0] if len(outputs) == 1 else (
        torch.cat(column) for column in zip(*outputs, strict=True))
    after = None
    if q is not None and returned is not None and next_cut is not None:
        after = Resume(next_cut, q, returned)
    return emit(region, t, on, out_w), after


def compiled_curve(curve: Curve) -> bool:
    """Whether the compiled window solves ``curve`` here (call where Numba is available).

    The linear curve always; the cubic one where the loop can round its multiply-adds as
    this torch's ``addcmul`` does (:func:`~..compiled.cubic.addcmul_is_fused`).
    """
    if curve == "linear":
        return True
    from evdown_torch.transforms.functional.compiled.cubic import addcmul_is_fused

    return addcmul_is_fused() is not None


def compiled_upkeep(t: Tensor) -> ModuleType | None:
    """The compiled twins of a bounded delay's upkeep where timestamps ``t`` take them.

    ``None`` where they do not (:func:`~..compiled.use_compiled`).

    :mod:`~..compiled.estimation_window`: ``held_knots``, ``merge_by_time`` and
    ``next_knots``, the same tensors as the eager functions. The one choice of both callers:
    :func:`estimate` (its held knots) and a session's step (``stream._upkeep``).
    """
    if not use_compiled(t):
        return None
    from evdown_torch.transforms.functional.compiled import estimation_window

    return estimation_window
