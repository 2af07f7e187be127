"""The estimators' settings: the threshold method's, the bounded delay and the curve."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from evdown_torch.checks import check_positive_float
from evdown_torch.transforms.functional.settings import ThresholdSettings

__all__ = ["Curve", "EstimationSettings"]

#: The pixels' curve: ``"linear"`` (method 4) or ``"cubic"`` (method 5, PCHIP).
Curve = Literal["linear", "cubic"]


@dataclass(frozen=True)
class EstimationSettings(ThresholdSettings):
    """The estimators' settings: the threshold method's, the bounded delay and the curve.

    Attributes:
        max_delay: ``D`` in the stream's time unit, or ``None`` (the paper's method, whole
            stream only).
        curve: ``"linear"`` or ``"cubic"``; the driver looks its solver up
            (:data:`~.driver.SOLVERS`).

    Example:
        >>> EstimationSettings((4, 4, 2), (2, 2), 0.5, max_delay=10, curve="cubic").lag
        2
    """

    max_delay: float | None = None
    curve: Curve = "linear"

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.max_delay is not None:
            check_positive_float("max_delay", self.max_delay)
        if self.curve not in ("linear", "cubic"):
            raise ValueError(f"curve must be 'linear' or 'cubic', got {self.curve!r}")

    @property
    def lag(self) -> int:
        """The lag, 1 (linear) or 2 (cubic), of output behind input.

        Output up to ``tau - lag * D`` is decided by input up to ``tau``.

        PCHIP slopes need one more knot than a polyline.
        """
        return 1 if self.curve == "linear" else 2
