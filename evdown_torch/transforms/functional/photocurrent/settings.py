"""PhotocurrentPooling's settings, checked once; the events mode's state; the frames' clock.

:class:`PhotocurrentSettings` is what both modes' kernels take
(:mod:`.events_mode` for the events mode, :mod:`.frames_mode` for the frames mode,
:mod:`.method` for the three kernels that pick the mode).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch.checks import (
    DEFAULT_TIME_UNIT,
    check_non_negative_float,
    check_positive_float,
    check_time_unit,
    time_unit_fraction,
)
from evdown_torch.transforms.functional.photocurrent.levels import check_contrast_range
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = ["FrameClock", "PhotocurrentSettings", "PhotocurrentState"]


class PhotocurrentState(NamedTuple):
    """State of a photocurrent pooling stream between chunks (events mode).

    Attributes:
        level: ``(H * W,)`` int64 level of every input pixel (ON +1, OFF -1), index ``y * W + x``.
        reference: ``(Ho * Wo,)`` int64 reference index ``q`` of every output region.
        last_t: ``()`` tensor, the latest timestamp seen (``None`` before any event).
    """

    level: Tensor
    reference: Tensor
    last_t: Tensor | None


class FrameClock(NamedTuple):
    """Frame times of a stream: frame ``k`` at offset ``min(k * period, duration)``.

    Offsets are from ``t_start``, in ticks (timestamp units); ``period = denominator /
    numerator`` exactly.

    Attributes:
        numerator: ``a * c`` for ``fps = a / b`` (``fps`` as the nearest fraction,
            ``b <= 10**6``) and ``time_unit = c / d`` seconds per tick
            (:func:`~evdown_torch.checks.time_unit_fraction`).
        denominator: ``b * d`` (so ``numerator / denominator`` frames per tick).
        duration: ``t_end - t_start`` as a float (ticks).
        tick: ``time_unit`` as the fraction ``c / d``, for frequencies in hertz.
    """

    numerator: int
    denominator: int
    duration: float
    tick: Fraction = Fraction(1, 10**6)

    @staticmethod
    def make(
        fps: float, duration: float | int, time_unit: float = DEFAULT_TIME_UNIT
    ) -> FrameClock:
        """The clock of a stream at ``fps`` frames per second.

        The stream lasts ``duration`` ticks of ``time_unit`` seconds.
        """
        fraction = Fraction(fps).limit_denominator(10**6)
        if fraction <= 0:
            raise ValueError(f"fps must be at least 1e-6 frames per second, got {fps!r}")
        tick = time_unit_fraction(time_unit)
        numerator = fraction.numerator * tick.numerator
        if duration * numerator >= 2**62:
            raise ValueError(
                f"fps={fps!r} over a stream of {duration} ticks of {time_unit!r} s gives frame "
                "indices beyond int64's exact range"
            )
        return FrameClock(numerator, fraction.denominator * tick.denominator, float(duration),
                          tick)

    def radians_per_tick(self, hz: float) -> float:
        """The angular frequency ``2 pi hz`` per tick (``hz`` per second)."""
        return 2 * math.pi * hz * self.tick.numerator / self.tick.denominator

    @property
    def period(self) -> float:
        """Frame period in ticks."""
        return self.denominator / self.numerator

    def frame_index(self, offset: Tensor) -> Tensor:
        """int64 index of the first frame at or after each ``offset`` (the frame holding it)."""
        if offset.is_floating_point():
            return torch.ceil(offset * (self.numerator / self.denominator)).to(torch.int64)
        scaled = offset * -self.numerator
        return -torch.div(scaled, self.denominator, rounding_mode="floor")

    def time(self, k: Tensor) -> Tensor:
        """float64 offset of frames ``k`` from ``t_start`` (frame -1 is at 0 too)."""
        return (k.to(torch.float64) * self.period).clamp_(0.0, self.duration)


@dataclass(frozen=True)
class PhotocurrentSettings(RegionSettings):
    """Photocurrent pooling's settings, checked and normalised once.

    Attributes:
        contrast: the input camera's contrast threshold in log units, in [1e-6, 50].
        threshold: the output pixel's contrast threshold in log units (``None``:
            ``contrast``; stored as a float).
        fps: frames per second of the frames mode, or ``None`` for the events mode.
        cutoff_hz: the frames mode's high-pass leak in Hz, >= 0.
        time_unit: seconds per timestamp unit for ``fps`` and ``cutoff_hz`` (frames mode
            only; stored as 1e-6 when not given there).
    """

    contrast: float = 0.2
    threshold: float | None = None
    fps: float | None = None
    cutoff_hz: float = 0.0
    time_unit: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        contrast = check_positive_float("contrast", self.contrast)
        threshold = contrast if self.threshold is None else self.threshold
        threshold = check_positive_float("threshold", threshold)
        check_contrast_range(contrast, threshold)
        object.__setattr__(self, "contrast", contrast)
        object.__setattr__(self, "threshold", threshold)
        cutoff = check_non_negative_float("cutoff_hz", self.cutoff_hz)
        object.__setattr__(self, "cutoff_hz", cutoff)
        if self.fps is None:
            if cutoff > 0:
                raise ValueError(f"cutoff_hz={cutoff!r} needs the frames mode: set fps")
            if self.time_unit is not None:
                raise ValueError(
                    f"time_unit={self.time_unit!r} converts the frames mode's fps and cutoff_hz; "
                    "the events mode (fps=None) has no rate to convert: set fps or leave "
                    "time_unit out"
                )
            return
        fps = check_positive_float("fps", self.fps)
        time_unit = check_time_unit(
            DEFAULT_TIME_UNIT if self.time_unit is None else self.time_unit
        )
        FrameClock.make(fps, 0, time_unit)
        object.__setattr__(self, "fps", fps)
        object.__setattr__(self, "time_unit", time_unit)

    @property
    def output_threshold(self) -> float:
        """The output pixel's contrast threshold, ``threshold`` or else ``contrast``."""
        return self.contrast if self.threshold is None else self.threshold
