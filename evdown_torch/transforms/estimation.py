"""LinearEstimation and CubicEstimation: the paper's log-luminance estimation downscalers."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

from evdown_torch.transforms._base import Session, ThresholdDownscaler
from evdown_torch.transforms.functional.estimation.method import ESTIMATION
from evdown_torch.transforms.functional.estimation.settings import Curve, EstimationSettings


@dataclass(frozen=True)
class _Estimation(ThresholdDownscaler, abstract=True):
    """What both estimators share: the bounded delay and its streaming session.

    Attributes:
        max_delay: ``D`` in the stream's time unit (a whole number for integer timestamps),
            or ``None`` (default) for the paper's method, which needs the whole stream.
    """

    max_delay: float | None = None

    method = ESTIMATION
    #: The pixels' curve (the settings' ``curve``, which picks the solver).
    curve: ClassVar[Curve] = "linear"

    @cached_property
    def settings(self) -> EstimationSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return EstimationSettings(*self.region_geometry(), self.threshold, self.max_delay,
                                  self.curve)

    @property
    def lag(self) -> int:
        """The lag (1 or 2) of output behind input, in units of ``max_delay``."""
        return self.settings.lag

    def algorithmic_delay(self) -> float:
        """``lag * max_delay``; ``inf`` without ``max_delay`` (the whole recording)."""
        return math.inf if self.max_delay is None else self.lag * self.max_delay

    def session(self) -> Session:
        """Start a streaming session (needs a finite ``max_delay``; see :meth:`stream`).

        Raises:
            ValueError: when ``max_delay`` is ``None``: the paper's estimators need the whole
                stream (each pixel's curve ramps towards its next event however far ahead).
        """
        if self.max_delay is None:
            raise ValueError(
                f"{type(self).__name__} with max_delay=None is the paper's method, which needs "
                "the whole stream; streaming needs a finite delay: set max_delay=D (in the "
                f"stream's time unit) and events come out at most {self.lag}*D after they happen"
            )
        return Session(self)


@dataclass(frozen=True)
class LinearEstimation(_Estimation):
    """Linear log-luminance estimation (docs/semantics.md, method 4), exact crossing times.

    Each input pixel's log-luminance is the polyline through its knots (one per distinct event
    time, at the level after its events there, ON +1 and OFF -1; held at 0 from the stream's
    start and at its last level up to the stream's end). Each output pixel watches the mean of
    its region's polylines with the DVS reference rule at contrast ``threshold`` and emits an
    event at every exact crossing time (rounded half up when timestamps are integers).

    Levels at knots are exact (integer arithmetic where no pixel is between knots, so
    ``factor=1, threshold=1`` returns the input). Elsewhere the kernel works in float64 and
    absorbs rounding where real arithmetic would be exact: a region within 1e-9 thresholds of
    a level is on it, and an integer crossing time within float error below a half tick (1e-9
    of a tick plus ``32 * 2**-53`` of its piece's length) rounds up. All time arithmetic is
    relative to breakpoints, so shifting the clock shifts the output exactly.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        threshold: contrast threshold on the region's mean level (in input events per pixel),
            > 0. It is used as the nearest fraction with denominator at most 10**6.
        max_delay: bounded delay ``D`` (docs/semantics.md, "Bounded delay"), in the stream's
            time unit and a whole number for integer timestamps: a pixel holds its level
            until ``D`` before its next knot, and a :meth:`session` returns each event at
            most ``D`` of stream time after it happens. ``None`` (default): the paper's
            method, batch only.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 0, 1], [1, 0, 10, 1]])
        >>> LinearEstimation((2, 1, 2), factor=(2, 1), threshold=0.25)(ev).tolist()
        [[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 5, 1], [0, 0, 10, 1]]
    """

    name = "linear"


@dataclass(frozen=True)
class CubicEstimation(_Estimation):
    """Cubic log-luminance estimation (docs/semantics.md, method 5).

    As :class:`LinearEstimation`, but each pixel's curve is the piecewise cubic Hermite
    interpolant of its knots with SciPy's ``PchipInterpolator`` slopes (two knots give a line,
    one a constant). Crossing times are solved on each monotone part of a region's cubic to
    about 1e-15 of the piece's length (rounded half up when timestamps are integers), with the
    same numerical conventions as :class:`LinearEstimation`.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        threshold: contrast threshold on the region's mean level (in input events per pixel),
            > 0. It is used as the nearest fraction with denominator at most 10**6.
        max_delay: bounded delay ``D`` as for :class:`LinearEstimation`; PCHIP slopes need
            one more knot, so a :meth:`session` returns each event at most ``2 * D`` after it
            happens. With ``D`` each pixel is at rest before the stream: its slope at its
            first knot is 0 (SciPy's end slope there would depend on input arbitrarily later).

    Example:
        Pixel (1, 0)'s curve rises faster than a straight line: on ``[0, 10]`` the sum of
        the region's two curves is ``1 + s - s**3 / 2`` (``s = t / 10``), which reaches
        ``2 * 0.25 * 3 = 1.5`` (the third level) where ``s**3 - 2 s + 1 = 0``, at
        ``s = (sqrt(5) - 1) / 2``: ``t = 6.18``, rounded to 6 (LinearEstimation gives 10).

        >>> import torch
        >>> ev = torch.tensor([[0, 0, 0, 1], [1, 0, 10, 1], [0, 0, 20, 0]])
        >>> CubicEstimation((2, 1, 2), factor=(2, 1), threshold=0.25)(ev).tolist()
        [[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 6, 1], [0, 0, 20, 0]]
    """

    name = "cubic"
    curve = "cubic"
