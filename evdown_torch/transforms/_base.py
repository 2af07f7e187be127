"""The shape every downscaling transform shares."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from evdown_torch.checks import check_factor, check_positive_float, check_sensor_size, output_size
from evdown_torch.events import Events, EventsLike, from_events, to_events
from evdown_torch.transforms.functional._reference import threshold_fraction


@dataclass(frozen=True)
class Downscaler:
    """Base of the downscaling transforms: settings, validation and the edge conversions.

    Subclasses are frozen dataclasses that implement :meth:`kernel`; ``__call__`` validates
    the events, converts them to :class:`~evdown_torch.events.Events`, calls the kernel and
    converts the result back to the caller's kind. Neither the input nor the transform is
    ever modified.

    Attributes:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``; pixel ``(x, y)`` goes to region
            ``(x // fx, y // fy)``.
    """

    #: The one setting that sets the output's event budget (see ``transforms.calibrate``);
    #: ``None`` for methods whose output count is fixed by the input.
    budget_setting: ClassVar[str | None] = None

    sensor_size: tuple[int, int, int]
    factor: int | tuple[int, int] = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensor_size", check_sensor_size(self.sensor_size))
        check_factor(self.factor, self.sensor_size)

    @property
    def factor_xy(self) -> tuple[int, int]:
        """The factor as a pair ``(fx, fy)``."""
        return check_factor(self.factor)

    @property
    def output_sensor_size(self) -> tuple[int, int, int]:
        """Output sensor size ``(ceil(W / fx), ceil(H / fy), P)``, for the next transform."""
        return output_size(self.sensor_size, self.factor_xy)

    def kernel(self, events: Events) -> Events:  # pragma: no cover - abstract
        """Downscale validated events; implemented by each method."""
        raise NotImplementedError

    def __call__(self, events: EventsLike) -> EventsLike:
        """Downscale events of any accepted kind and return the same kind.

        Args:
            events: a Tonic structured array (fields x, y, t, p in any order), a tensor of
                shape ``(N, 4)`` with columns ``(x, y, t, p)``, or Events.

        Returns:
            The downscaled events, sorted by ``t``, in the input's kind, dtype and polarity
            encoding, with coordinates inside :attr:`output_sensor_size`.
        """
        ev, fmt = to_events(events, self.sensor_size)
        return from_events(self.kernel(ev), fmt)


@dataclass(frozen=True)
class ThresholdDownscaler(Downscaler):
    """Base of the log-luminance methods: a DVS reference rule at a contrast threshold.

    Attributes:
        threshold: contrast threshold on a region's mean level (in input events per pixel),
            > 0. It is used as the nearest fraction with denominator at most 10**6, so
            decimal thresholds such as 0.01 are exact.

    A call counts its output before building it and raises a ``ValueError`` naming the count
    when it would exceed :func:`evdown_torch.set_max_output_events` (100 million events by
    default): a threshold far below the level steps of a region asks for that many. The
    linear and cubic estimators also refuse integer timestamps spanning 2**53 or more, whose
    crossing times float64 cannot hold.
    """

    budget_setting: ClassVar[str | None] = "threshold"

    threshold: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "threshold", check_positive_float("threshold", self.threshold))
        threshold_fraction(self.threshold)
