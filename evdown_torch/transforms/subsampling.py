"""The subsamplers: peers that spend an event budget by keeping input events, then Downsample.

docs/semantics.md, "Subsamplers": each keeps or drops the input events at the input
resolution, causally, one seeded draw per event
(:func:`~evdown_torch.transforms.functional.draws.event_uniforms`, the same in a batch call
and in a session), then divides the coordinates by the factor. Each has one budget setting
that :func:`~evdown_torch.transforms.calibrate.calibrate` searches.
"""

from __future__ import annotations

__all__ = ["DensitySubsampling", "PoissonSubsampling"]

from dataclasses import dataclass
from functools import cached_property

from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.functional.density import DENSITY, DensitySettings
from evdown_torch.transforms.functional.poisson import POISSON, PoissonSettings


@dataclass(frozen=True)
class DensitySubsampling(Downscaler):
    """Keep events where their polarity is dense nearby, then Downsample (method 9).

    After Araghi et al. (CVPR Workshops 2025), the subsampler that kept the most accuracy at
    small budgets in their comparison. Per polarity, each pixel's count decays as
    ``exp(-dt / tau)`` and gains 1 at each event; an event's density is the Gaussian-weighted
    (``sigma = k / 5``, 1 at the centre) sum of the counts over the ``k x k`` patch around
    it, and the event is kept iff its draw ``u_e < s * density``. Causal and streamable; the
    draws are seeded by the event's place in the recording and ``seed``.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        tau: decay time constant, in the stream's time unit (microseconds for Tonic), > 0.
        k: patch side, an odd positive integer.
        s: the budget setting, > 0 (``s >= 1`` keeps every event).
        seed: non-negative integer mixed into every draw.

    Example:
        A burst of 100 events at one pixel, and 16 lone events 1 ms apart along row 12: at
        ``s = 0.05`` nearly all the burst is kept and nearly none of the lone events.

        >>> import torch
        >>> burst = [[5, 5, t, 1] for t in range(0, 200, 2)]
        >>> lone = [[x, 12, 1000 * x, 1] for x in range(16)]
        >>> sub = DensitySubsampling((16, 16, 2), factor=2, tau=1000, s=0.05)
        >>> out = sub(torch.tensor(burst + lone))
        >>> int((out[:, 1] == 2).sum()), int((out[:, 1] == 6).sum())  # burst, lone (y // 2)
        (93, 1)
    """

    budget_setting = "s"
    method = DENSITY
    name = "density"

    tau: float = 30_000.0
    k: int = 7
    s: float = 1.0
    seed: int = 0

    @cached_property
    def settings(self) -> DensitySettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return DensitySettings(*self.region_geometry(), self.tau, self.k, self.s, self.seed)


@dataclass(frozen=True)
class PoissonSubsampling(Downscaler):
    """Keep events by a Poisson probability map under a running budget cap (method 10).

    After POLED (CVPR Workshops 2025), re-implemented from the paper, without its spatial
    prior and sigmoid reshaping. Per polarity, the events of each window of ``window`` give
    the next window's map ``P(j) = min(1, alpha * B(j) / mean B)``, ``B`` the Gaussian blur
    (sigma 2 pixels) of ``1 - exp(-count)``; an event is kept iff its draw ``u_e < P`` and
    keeping it leaves at most ``alpha`` of the events seen so far kept. Causal and
    streamable; the draws are seeded by the event's place in the recording and ``seed``.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        window: window length in the stream's time unit (microseconds for Tonic), > 0; a
            whole number for integer timestamps.
        alpha: the budget setting, the fraction of events kept at most, in ``[1e-6, 1]``.
        seed: non-negative integer mixed into every draw.

    Example:
        At ``alpha = 0.25`` at most a quarter of 400 events are kept, and a session fed the
        stream in two chunks keeps the same ones:

        >>> import torch
        >>> ev = torch.tensor([[t % 4, 0, t * 100, 1] for t in range(400)])
        >>> sub = PoissonSubsampling((4, 1, 2), factor=1, window=1000, alpha=0.25)
        >>> out = sub(ev)
        >>> session = sub.session()
        >>> len(out) <= 100, bool(torch.cat([session(ev[:150]), session(ev[150:])]).equal(out))
        (True, True)
    """

    budget_setting = "alpha"
    method = POISSON
    name = "poisson"

    window: float = 6_000.0
    alpha: float = 1.0
    seed: int = 0

    @cached_property
    def settings(self) -> PoissonSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return PoissonSettings(*self.region_geometry(), self.window, self.alpha, self.seed)
