"""The settings of LIF pooling (method 6), validated and normalised once.

:class:`LIFSettings` is the one home of the LIF neuron's settings and of their checks: the
transform :class:`~evdown_torch.LIFPooling` builds one from its fields, its kernels
(:func:`~evdown_torch.transforms.functional.lif.pooling.lif_pooling`, the streaming pair in
:mod:`~evdown_torch.transforms.functional.lif.stream`) take one, and the module
:class:`~evdown_torch.models.SpikingPooling` builds one from its arguments (Norse's
``LIFParameters`` play the same part there). Every value is a Python ``float`` (or the reset
name) once built, so no caller re-normalises.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple, cast

from evdown_torch.checks import (
    check_choice,
    check_non_negative_float,
    check_positive_float,
    check_time_constant,
    check_unit_interval,
)
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = [
    "DEFAULT_DT",
    "DEFAULT_TAU",
    "DEFAULT_TAU_STEPS",
    "DEFAULT_THRESHOLD",
    "DEFAULT_WEIGHT",
    "RESET_MECHANISMS",
    "LIFNeuron",
    "LIFPoolingSettings",
    "LIFSettings",
    "ResetMechanism",
    "decay_factor",
]

ResetMechanism = Literal["subtract", "zero", "none"]
RESET_MECHANISMS: tuple[str, ...] = ("subtract", "zero", "none")

#: Defaults of LIF pooling (transform and module): a neuron needs about four same-polarity input
#: events within a few time constants to fire (see :class:`~evdown_torch.LIFPooling`).
DEFAULT_DT = 1000.0
DEFAULT_THRESHOLD = 1.0
DEFAULT_WEIGHT = 0.3
#: The leak when neither ``tau`` nor ``beta`` is given: ``tau`` = 10 steps.
DEFAULT_TAU_STEPS = 10.0
DEFAULT_TAU = DEFAULT_TAU_STEPS * DEFAULT_DT


def decay_factor(dt: float, tau: float) -> float:
    """Membrane decay per time step, ``beta = exp(-dt / tau)``.

    Args:
        dt: length of a time step, positive.
        tau: membrane time constant in the unit of ``dt``, positive; ``math.inf`` gives
            ``beta = 1`` (no leak, integrate-and-fire).

    Returns:
        ``beta`` in ``[0, 1]``: 0 as ``tau -> 0`` (no memory), 1 as ``tau -> inf``.

    Example:
        >>> round(decay_factor(1000.0, 10_000.0), 6)
        0.904837
    """
    dt = check_positive_float("dt", dt)
    tau = check_time_constant("tau", tau)
    return math.exp(-dt / tau)


class LIFNeuron(NamedTuple):
    """What the neuron update needs.

    In the order and names of :class:`~evdown_torch.models.SpikingPooling`'s keyword
    arguments.
    """

    beta: float
    threshold: float
    weight: float
    mutual_inhibition: float
    reset_mechanism: ResetMechanism


@dataclass(frozen=True)
class LIFSettings:
    """The settings of one LIF pooling neuron per region and polarity, checked once.

    The leak is given by exactly one of ``tau`` and ``beta = exp(-dt / tau)``; with neither,
    ``tau`` is ``DEFAULT_TAU_STEPS`` (10) steps. Times (``dt``, ``tau``) are in the stream's
    own unit. Once built, every number is a float, ``beta`` is always set and ``tau`` is set
    unless the leak was given as ``beta``.

    Attributes:
        dt: step length, positive.
        tau: membrane time constant, positive (``math.inf``: no leak), or ``None``.
        threshold: firing threshold, positive (a neuron fires when its membrane exceeds it).
        weight: weight of each same-polarity input event, positive.
        mutual_inhibition: weight of each opposite-polarity input event, subtracted, ``>= 0``.
        reset_mechanism: ``"subtract"``, ``"zero"`` or ``"none"`` (snntorch's meanings).
        beta: membrane decay per step in ``[0, 1]``, instead of ``tau``.

    Raises:
        TypeError, ValueError: for a setting of the wrong type or out of range, or both
            ``tau`` and ``beta``.

    Example:
        >>> s = LIFSettings(dt=1000, tau=10_000, weight=1)
        >>> s.weight, round(s.beta, 6)
        (1.0, 0.904837)
        >>> LIFSettings(dt=1, beta=0.5).tau is None
        True
    """

    dt: float = DEFAULT_DT
    tau: float | None = None
    threshold: float = DEFAULT_THRESHOLD
    weight: float = DEFAULT_WEIGHT
    mutual_inhibition: float = 0.0
    reset_mechanism: ResetMechanism = "subtract"
    beta: float | None = None

    def __post_init__(self) -> None:
        dt = check_positive_float("dt", self.dt)
        tau, beta = self.tau, self.beta
        if beta is not None:
            if tau is not None:
                raise ValueError(
                    f"give the leak as tau or as beta, not both; got tau={tau!r} and beta={beta!r}"
                )
            beta = check_unit_interval("beta", beta)
        else:
            tau = DEFAULT_TAU_STEPS * dt if tau is None else check_time_constant("tau", tau)
            beta = math.exp(-dt / tau)
        normalised = {
            "dt": dt,
            "tau": tau,
            "beta": beta,
            "threshold": check_positive_float("threshold", self.threshold),
            "weight": check_positive_float("weight", self.weight),
            "mutual_inhibition": check_non_negative_float(
                "mutual_inhibition", self.mutual_inhibition
            ),
            "reset_mechanism": check_choice(
                "reset_mechanism", self.reset_mechanism, RESET_MECHANISMS
            ),
        }
        for name, value in normalised.items():
            object.__setattr__(self, name, value)

    @property
    def constants(self) -> LIFNeuron:
        """The neuron's settings, as :class:`~evdown_torch.models.SpikingPooling` takes them.

        ``beta``, ``threshold``, ``weight``, ``mutual_inhibition`` and ``reset_mechanism``.
        """
        beta = cast(float, self.beta)  # set by __post_init__
        return LIFNeuron(
            beta, self.threshold, self.weight, self.mutual_inhibition, self.reset_mechanism
        )


@dataclass(frozen=True)
class LIFPoolingSettings(RegionSettings):
    """What the LIF pooling kernels take: the region geometry and the neuron's settings.

    Attributes:
        sensor_size: as :class:`~evdown_torch.transforms.functional.RegionSettings`.
        factor: as :class:`~evdown_torch.transforms.functional.RegionSettings`.
        neuron: the neuron's :class:`LIFSettings` (what ``LIFPooling.settings`` returns and
            :class:`~evdown_torch.models.SpikingPooling` shares).
    """

    neuron: LIFSettings
