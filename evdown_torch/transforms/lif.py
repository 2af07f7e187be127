"""LIF pooling transform (method 6) and the weight calibration helper."""

from __future__ import annotations

__all__ = ["LIFPooling", "calibrate_weight"]

from dataclasses import dataclass, fields, replace
from functools import cached_property

from evdown_torch.checks import check_positive_float
from evdown_torch.events import EventsLike, sort_by_time, to_events
from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.functional.lif.settings import (
    DEFAULT_DT,
    DEFAULT_TAU,
    DEFAULT_THRESHOLD,
    DEFAULT_WEIGHT,
    LIFPoolingSettings,
    LIFSettings,
    ResetMechanism,
)
from evdown_torch.transforms.functional.lif.stream import LIF_POOLING


@dataclass(frozen=True)
class LIFPooling(Downscaler):
    """Spiking pooling of an event stream: one LIF neuron per output region and polarity.

    The stream is binned into steps of ``dt`` from its first timestamp ``t_start``; in each step
    the events of a ``fx x fy`` block drive the block's two neurons (weight ``+weight`` from
    same-polarity events, ``-mutual_inhibition`` from the other polarity), which follow
    ``snntorch.Leaky`` with ``beta = exp(-dt / tau)`` (see
    :class:`~evdown_torch.models.SpikingPooling`, which computes the same spikes on the
    dense ``ToFrame``-like tensor, and which
    :meth:`~evdown_torch.models.SpikingPooling.from_transform` builds). A spike in step ``k``
    becomes an event at the block's coordinates with the neuron's polarity, at
    ``t_start + (k + 1) * dt`` clipped to ``t_end``. The kernel is event-driven: a neuron is
    touched only at the steps where its block has events, the silences in between (decay, and
    a neuron firing on above threshold) are solved in closed form, so the cost follows the
    events, not steps x regions (see :func:`~evdown_torch.transforms.functional.lif_pooling`,
    also for the float32 rounding over a silence, the only difference from stepping).

    Choosing the settings. ``dt`` and ``tau`` are in the stream's time unit (microseconds for
    Tonic datasets; nothing is rescaled). A neuron fires once its membrane *exceeds*
    ``threshold``; without leak that takes ``floor(threshold / weight) + 1`` same-polarity
    events, then one spike per ``threshold / weight`` further events (subtract reset). The
    output rate is very sensitive to ``weight`` (as the paper found), so:

    - ``weight`` sets the gain: about ``weight / threshold`` output events per same-polarity
      input event in a busy block. Raising it keeps more events and more detail (at
      ``weight > threshold`` every active block and step fires, like Downsample binned to
      ``dt``); lowering it keeps only the busiest blocks.
    - ``tau`` sets how long evidence is kept: events of a block count together when they fall
      within about ``tau``. A short ``tau`` fires only for dense bursts and removes isolated
      (noise) events; a long ``tau`` also passes slow, sparse activity, and noise with it.
      ``tau = math.inf`` is a pure integrate-and-fire neuron.
    - ``threshold`` only matters relative to ``weight``.
    - ``dt`` is the output's time resolution: output events fall on the ends of steps.
    - ``mutual_inhibition`` makes ON and OFF events of a block cancel, suppressing flicker.

    The defaults (``dt`` = 1 ms, ``tau`` = 10 ms, ``weight`` = 0.3, ``threshold`` = 1: four
    same-polarity events within a few milliseconds fire a neuron) suit microsecond streams of
    DVS sensors at factors 2 to 4, e.g. a 128x128 DVS Gesture stream at factor 4 keeps the moving
    hands and drops background noise. :func:`calibrate_weight` picks the weight that gives a
    wanted output rate on a sample.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        dt: step length, in the stream's time unit, positive.
        tau: membrane time constant, in the stream's time unit, positive (``math.inf``: no
            leak).
        threshold: firing threshold, positive.
        weight: weight of each same-polarity input event, positive.
        mutual_inhibition: weight of each opposite-polarity input event, subtracted (0: none).
        reset_mechanism: ``"subtract"``, ``"zero"`` or ``"none"`` (snntorch's meanings).

    The settings are checked and normalised (to floats) once, by :class:`LIFSettings`
    (:attr:`settings`), which the kernels and :class:`~evdown_torch.models.SpikingPooling` share.

    A call that would emit more events than the output limit raises a ``ValueError`` naming
    the count instead: a neuron kept above threshold, e.g. with no leak and
    ``reset_mechanism="none"``, fires at every step of a silence, however long. The limit is
    the package's one (:func:`evdown_torch.max_output_events`, 10**8 by default; ``with
    evdown_torch.max_output_events(None):`` removes it); the former field
    ``max_output_events`` is gone.

    Raises:
        ValueError: at call time, when ``dt`` would cut the stream into more than ``2**62``
            steps (an int64 step index) or the output exceeds the output limit.

    Example:
        >>> import numpy as np
        >>> dtype = np.dtype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")])
        >>> ev = np.array([(0, 0, True, 100), (1, 0, True, 300), (0, 1, True, 500),
        ...                (1, 1, True, 700), (3, 3, False, 5000)], dtype=dtype)
        >>> pool = LIFPooling((4, 4, 2), factor=2)
        >>> pool(ev).tolist()  # four ON events in block (0, 0) within 1 ms
        [(0, 0, True, 1100)]
    """

    dt: float = DEFAULT_DT
    tau: float = DEFAULT_TAU
    threshold: float = DEFAULT_THRESHOLD
    weight: float = DEFAULT_WEIGHT
    mutual_inhibition: float = 0.0
    reset_mechanism: ResetMechanism = "subtract"

    method = LIF_POOLING
    name = "lif"
    budget_setting = "weight"

    def __post_init__(self) -> None:
        super().__post_init__()
        neuron = self.settings.neuron
        for field in fields(LIFSettings):  # the neuron's normalised values back
            if field.name != "beta":
                object.__setattr__(self, field.name, getattr(neuron, field.name))

    @cached_property
    def settings(self) -> LIFPoolingSettings:
        """The checked settings the kernels take, the region geometry and the neuron's.

        The neuron's :class:`~evdown_torch.transforms.functional.LIFSettings`
        (``settings.neuron``) is shared with
        :class:`~evdown_torch.models.SpikingPooling` (``SpikingPooling.from_transform``).
        """
        neuron = LIFSettings(
            dt=self.dt, tau=self.tau, threshold=self.threshold, weight=self.weight,
            mutual_inhibition=self.mutual_inhibition, reset_mechanism=self.reset_mechanism,
        )
        return LIFPoolingSettings(*self.region_geometry(), neuron)

    @property
    def beta(self) -> float:
        """Membrane decay per step, ``exp(-dt / tau)``."""
        return self.settings.neuron.constants.beta

    def algorithmic_delay(self) -> float:
        """One time step: a step's spikes come out once the stream reaches the step's end."""
        return float(self.dt)


#: How far below its target :func:`calibrate_weight` may end before it calls the target
#: unreachable (the contract's 5 %).
MISS_TOLERANCE = 0.05


def calibrate_weight(
    events: EventsLike,
    sensor_size: tuple[int, int, int],
    factor: int | tuple[int, int] = 4,
    *,
    target_ratio: float | None = None,
    target_rate: float | None = None,
    time_unit: float | None = None,
    dt: float = DEFAULT_DT,
    tau: float = DEFAULT_TAU,
    threshold: float = DEFAULT_THRESHOLD,
    mutual_inhibition: float = 0.0,
    reset_mechanism: ResetMechanism = "subtract",
    rtol: float = 1e-3,
    max_evaluations: int = 40,
) -> float:
    """The LIFPooling ``weight`` whose output has a wanted event rate on a sample stream.

    The LIF case of :func:`~evdown_torch.transforms.calibrate.calibrate` (the weight is
    LIFPooling's budget setting), on one sample stream: the output count grows with the
    weight (stepwise), and the deterministic search runs the (vectorised) transform once per
    weight it tries, starting from ``threshold``. Give the target as exactly one of
    ``target_ratio`` (output events per input event) and ``target_rate`` (output events per
    second, timestamps counting ``time_unit`` seconds).

    Args:
        events: the sample, any kind :class:`LIFPooling` accepts.
        sensor_size: ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        target_ratio: wanted ``output events / input events``, positive.
        target_rate: wanted output events per second, positive.
        time_unit: seconds per timestamp unit, for ``target_rate`` only (default 1e-6:
            microseconds; see :func:`~evdown_torch.checks.check_time_unit`).
        dt: :class:`LIFPooling`'s step length, in the stream's time unit.
        tau: its membrane time constant, in the unit of ``dt``.
        threshold: its firing threshold.
        mutual_inhibition: its weight of each opposite-polarity input event.
        reset_mechanism: its reset, ``"subtract"``, ``"zero"`` or ``"none"``.
        rtol: stop once the output count is within this fraction of the target.
        max_evaluations: at most this many runs of the transform.

    Returns:
        The weight whose output count is closest to the target among those evaluated (within
        ``rtol`` of it wherever the stepwise count can get there).

    Raises:
        ValueError: for an empty sample, an unreachable target or a bad setting (also a
            ``time_unit`` with ``target_ratio``, which has no time in it).

    Example:
        >>> import numpy as np
        >>> rng = np.random.default_rng(0)
        >>> dtype = np.dtype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")])
        >>> ev = np.zeros(20_000, dtype=dtype)
        >>> ev["x"], ev["y"] = rng.integers(0, 32, (2, 20_000))
        >>> ev["p"], ev["t"] = rng.random(20_000) < 0.5, np.sort(rng.integers(0, 10**6, 20_000))
        >>> w = calibrate_weight(ev, (32, 32, 2), 4, target_ratio=0.1)
        >>> out = LIFPooling((32, 32, 2), 4, weight=w)(ev)
        >>> abs(len(out) / len(ev) - 0.1) < 0.01
        True
    """
    from evdown_torch.transforms.calibrate import BudgetTarget, calibration

    if (target_ratio is None) == (target_rate is None):
        raise ValueError("give exactly one of target_ratio and target_rate")
    if target_ratio is not None:
        target = BudgetTarget("ratio", check_positive_float("target_ratio", target_ratio),
                              time_unit)
    else:
        target = BudgetTarget("rate", check_positive_float("target_rate", target_rate),
                              time_unit)
    template = LIFPooling(
        sensor_size,
        factor,
        dt=dt,
        tau=tau,
        threshold=threshold,
        mutual_inhibition=mutual_inhibition,
        reset_mechanism=reset_mechanism,
        weight=threshold,
    )
    sample, _ = to_events(events, template.sensor_size)
    if sample.num_events == 0:
        raise ValueError("calibrate_weight needs a non-empty sample stream")
    sample = sort_by_time(sample)
    found = calibration(template, [sample], target, rtol=rtol, max_evaluations=max_evaluations)
    if found.count < (1 - MISS_TOLERANCE) * found.target:
        larger = replace(found.transform, weight=4 * found.value).kernel(sample).num_events
        if larger < (1 - MISS_TOLERANCE) * found.target:
            raise ValueError(
                f"no weight up to {4 * found.value:.3g} reaches the target of "
                f"{found.target:.0f} output events (at most {larger} on this sample after "
                f"{found.evaluations + 1} evaluations); lower the target"
            )
    return found.value
