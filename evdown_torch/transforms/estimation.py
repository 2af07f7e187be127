"""LinearEstimation and CubicEstimation: the paper's log-luminance estimation downscalers."""

from __future__ import annotations

from dataclasses import dataclass

from evdown_torch.events import Events
from evdown_torch.transforms._base import ThresholdDownscaler
from evdown_torch.transforms.functional.cubic import cubic_estimation
from evdown_torch.transforms.functional.linear import linear_estimation


@dataclass(frozen=True)
class LinearEstimation(ThresholdDownscaler):
    """Linear log-luminance estimation (docs/semantics.md, method 4), exact crossing times.

    Each input pixel's log-luminance is the polyline through its knots (one per distinct event
    time, at the level after its events there, ON +1 and OFF -1; held at 0 from the stream's
    start and at its last level up to the stream's end). Each output pixel watches the mean of
    its region's polylines with the DVS reference rule at contrast ``threshold`` and emits an
    event at every exact crossing time (rounded half up when timestamps are integers).

    Levels at knots are exact (integer arithmetic where no pixel is between knots, so
    ``factor=1, threshold=1`` returns the input). Elsewhere the kernel works in float64 and
    absorbs rounding where real arithmetic would be exact: a region within 1e-9 thresholds of
    a level is on it, and an integer crossing time within 1e-9 of a tick below a half rounds
    up. All time arithmetic is relative to breakpoints, so shifting the clock shifts the
    output exactly.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        threshold: contrast threshold on the region's mean level (in input events per pixel),
            > 0. It is used as the nearest fraction with denominator at most 10**6.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 0, 1], [1, 0, 10, 1]])
        >>> LinearEstimation((2, 1, 2), factor=(2, 1), threshold=0.25)(ev).tolist()
        [[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 5, 1], [0, 0, 10, 1]]
    """

    def kernel(self, events: Events) -> Events:
        """Apply :func:`~evdown_torch.transforms.functional.linear.linear_estimation`."""
        return linear_estimation(
            events, sensor_size=self.sensor_size, factor=self.factor_xy, threshold=self.threshold
        )


@dataclass(frozen=True)
class CubicEstimation(ThresholdDownscaler):
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

    def kernel(self, events: Events) -> Events:
        """Apply :func:`~evdown_torch.transforms.functional.cubic.cubic_estimation`."""
        return cubic_estimation(
            events, sensor_size=self.sensor_size, factor=self.factor_xy, threshold=self.threshold
        )
