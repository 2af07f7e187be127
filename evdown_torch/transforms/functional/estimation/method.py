"""The estimators as a method: the ``ESTIMATION`` bundle and the keyword functions.

Both estimators share one method; their settings' ``curve`` picks the solver
(:data:`~.driver.SOLVERS`). ``estimation_init`` / ``estimation_step`` / ``estimation_finish``
(:mod:`.stream`) stream a bounded delay; :func:`estimation_whole` and
:func:`estimation_stacked` run a whole stream or a batch through the driver
(:func:`~.driver.estimate`). :func:`linear_estimation` and :func:`cubic_estimation` are the
functional faces, with the settings as keywords.
"""

from __future__ import annotations

from evdown_torch.collate import EventBatch
from evdown_torch.events import Events
from evdown_torch.transforms.functional.batch import Stacked, run_stacked
from evdown_torch.transforms.functional.estimation.driver import estimate
from evdown_torch.transforms.functional.estimation.settings import EstimationSettings
from evdown_torch.transforms.functional.estimation.stream import (
    WindowState,
    estimation_finish,
    estimation_init,
    estimation_step,
)
from evdown_torch.transforms.functional.protocol import Method

__all__ = [
    "ESTIMATION",
    "cubic_estimation",
    "estimation_stacked",
    "estimation_whole",
    "linear_estimation",
]


def estimation_whole(events: Events, settings: EstimationSettings) -> Events:
    """The whole stream (any order) in one call (:func:`~.driver.estimate`)."""
    return estimate(events, settings)


def estimation_stacked(batch: EventBatch, settings: EstimationSettings) -> EventBatch:
    """The whole-stream kernel once on the stacked batch, with each recording's own span."""

    def kernel(stacked: Stacked) -> Events:
        return estimate(stacked.events, settings, recording_spans=(stacked.starts, stacked.ends))

    return run_stacked(batch, kernel, sensor_size=settings.sensor_size, factor=settings.factor)


#: LinearEstimation's and CubicEstimation's kernels (the settings' ``curve`` tells them apart).
ESTIMATION: Method[EstimationSettings, WindowState] = Method(
    estimation_init, estimation_step, estimation_finish,
    whole=estimation_whole, stacked=estimation_stacked,
)


def linear_estimation(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    threshold: float,
    max_delay: float | None = None,
) -> Events:
    """Downscale by linear log-luminance estimation (docs/semantics.md, method 4).

    Each pixel's log-luminance is the polyline through its knots (see
    ``estimation.knots``); each region's mean ``M_r`` (sum of its
    pixels' polylines over ``n_r``) is watched by the DVS reference rule at contrast
    ``threshold`` over ``[t_start, t_end]``, from level 0 just before ``t_start``. Events get
    the exact crossing times, rounded half up to integers when ``t`` is int64.

    The kernel sweeps each region's breakpoints once. ``n_r * M_r`` at a breakpoint is an
    exact integer (the levels of the pixels' latest knots) plus the progress of the pixels
    strictly inside a segment; that progress is the running integral of the region's slope,
    whose sum is kept in fixed point so that it does not drift, and it is exactly 0 wherever no
    pixel is inside a segment. All time arithmetic is relative to breakpoints, so shifting the
    clock shifts the output exactly.

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        threshold: contrast threshold ``theta`` on the region's mean level, > 0, used as the
            nearest fraction with denominator at most 10**6.
        max_delay: bounded delay ``D`` in the stream's time unit (docs/semantics.md,
            "Bounded delay"; a whole number for int64 ``t``), or ``None`` for the paper's
            method. With ``D`` a pixel holds its level until ``D`` before its next knot.

    Returns:
        Output events sorted by ``t``, ``t`` of the input's dtype.

    Example:
        >>> ev = Events.from_columns([0, 1], [0, 0], [0, 10], [1, 1])
        >>> out = linear_estimation(ev, sensor_size=(2, 1, 2), factor=(2, 1), threshold=0.25)
        >>> out.t.tolist(), out.p.tolist()
        ([0, 0, 5, 10], [True, True, True, True])
    """
    settings = EstimationSettings(sensor_size, factor, threshold, max_delay, curve="linear")
    return estimate(events, settings)


def cubic_estimation(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    threshold: float,
    max_delay: float | None = None,
) -> Events:
    """Downscale by cubic log-luminance estimation (docs/semantics.md, method 5).

    Each pixel's log-luminance is the piecewise cubic Hermite interpolant of its knots (see
    ``estimation.knots``) with SciPy's ``PchipInterpolator``
    slopes; each region's mean ``M_r`` is watched by the DVS reference rule at contrast
    ``threshold`` over ``[t_start, t_end]``, from level 0 just before ``t_start``. Events get
    the crossing times, rounded half up to integers when ``t`` is int64.

    Between two breakpoints (consecutive knot times of a region) ``M_r`` is one cubic, known
    from its values and derivatives at both ends. Those are sums over the region's pixels: an
    exact integer part (the levels of pixels with a knot there) plus the pixels strictly inside
    a segment, evaluated in each segment's normalised time. Each piece is split at the roots of
    its derivative into monotone moves for the reference rule, and each crossing is solved on
    its monotone move, in the piece's normalised time, by safeguarded Newton iterations to
    about 1e-15 of the piece's length.

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        threshold: contrast threshold ``theta`` on the region's mean level, > 0, used as the
            nearest fraction with denominator at most 10**6.
        max_delay: as there; besides, each pixel's slope at its first knot is 0 (at rest
            before the stream).

    Returns:
        Output events sorted by ``t``, ``t`` of the input's dtype.

    Example:
        The region's curve rises faster than the polyline: its third level at ``t = 6.18``
        (rounded to 6), where the linear estimate reaches it at 10.

        >>> ev = Events.from_columns([0, 1, 0], [0, 0, 0], [0, 10, 20], [1, 1, 0])
        >>> out = cubic_estimation(ev, sensor_size=(2, 1, 2), factor=(2, 1), threshold=0.25)
        >>> out.t.tolist(), out.p.tolist()
        ([0, 0, 6, 20], [True, True, True, False])
    """
    settings = EstimationSettings(sensor_size, factor, threshold, max_delay, curve="cubic")
    return estimate(events, settings)
