"""The settings every region method shares, checked and normalised once.

A method is a frozen settings dataclass plus three pure kernels (``init_state``, ``step``,
``finish``; see :class:`~evdown_torch.transforms._base.Method`). The settings here are the
region geometry (:class:`RegionSettings`) and, for the methods watching a region with the
DVS reference rule, the contrast threshold (:class:`ThresholdSettings`). Methods with more
settings extend them beside their kernels (LIF: :mod:`.lif.settings`). A transform builds its
settings in ``__post_init__``: that is where every setting is checked, and the only place.
"""

from __future__ import annotations

from dataclasses import dataclass

from evdown_torch.checks import check_factor, check_positive_float, check_sensor_size, output_size
from evdown_torch.transforms.functional.reference import threshold_fraction

__all__ = ["RegionSettings", "ThresholdSettings"]


@dataclass(frozen=True)
class RegionSettings:
    """Input sensor and downscaling factor.

    Attributes:
        sensor_size: input ``(W, H, P)``, normalised to a tuple of ints.
        factor: ``(fx, fy)``; pixel ``(x, y)`` belongs to region ``(x // fx, y // fy)``.
            Given as one positive integer or a pair; stored as the pair.

    Example:
        >>> RegionSettings((5, 4, 2), 2)
        RegionSettings(sensor_size=(5, 4, 2), factor=(2, 2))
        >>> RegionSettings((5, 4, 2), 2).output_sensor_size
        (3, 2, 2)
    """

    sensor_size: tuple[int, int, int]
    factor: tuple[int, int]

    def __post_init__(self) -> None:
        sensor_size = check_sensor_size(self.sensor_size)
        object.__setattr__(self, "sensor_size", sensor_size)
        object.__setattr__(self, "factor", check_factor(self.factor, sensor_size))

    @property
    def output_sensor_size(self) -> tuple[int, int, int]:
        """``(ceil(W / fx), ceil(H / fy), P)``."""
        return output_size(self.sensor_size, self.factor)


@dataclass(frozen=True)
class ThresholdSettings(RegionSettings):
    """Region geometry plus the contrast threshold of the DVS reference rule.

    Attributes:
        threshold: contrast threshold on a region's mean level (input events per pixel), > 0,
            a float; used as the nearest fraction with denominator at most 10**6.
    """

    threshold: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        threshold = check_positive_float("threshold", self.threshold)
        threshold_fraction(threshold)
        object.__setattr__(self, "threshold", threshold)
