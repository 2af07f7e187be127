"""The thinning control: Downsample, then keep each event at random, seeded by the recording."""

from __future__ import annotations

__all__ = ["ThinnedDownsample", "recording_seed"]

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

from evdown_torch.events import Events
from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.functional.thinning import (
    THINNING,
    ThinningSettings,
    recording_seed,
    thinning_draws,
)


@dataclass(frozen=True)
class ThinnedDownsample(Downscaler):
    """Downsample, then keep each output event independently with probability ``keep``.

    The *thinning control* of the evaluation (docs/semantics.md, "Event budget"): it spends an
    event budget with no method at all, every kept event at its downsampled place and time.
    The random draws are seeded by the recording itself (``recording_seed`` of the input
    stream and ``seed``), so a recording is always thinned the same way, in any order, batch
    or worker process, and nothing reads global random state. ``keep`` is the budget setting
    that :func:`~evdown_torch.transforms.calibrate.calibrate` searches.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        keep: probability of keeping each event, in ``[0, 1]`` (1: plain Downsample).
        seed: non-negative integer mixed into every recording's seed.

    Example:
        >>> import torch
        >>> ev = torch.stack([torch.arange(1000) % 8, torch.arange(1000) % 4,
        ...                   torch.arange(1000), torch.arange(1000) % 2], 1)
        >>> control = ThinnedDownsample((8, 4, 2), factor=2, keep=0.25)
        >>> out = control(ev)
        >>> 200 < len(out) < 300, bool(out.equal(control(ev)))
        (True, True)
    """

    budget_setting = "keep"
    method = THINNING

    keep: float = 1.0
    seed: int = 0

    @cached_property
    def settings(self) -> ThinningSettings:
        """The checked settings the kernel takes (built once, in ``__post_init__``)."""
        return ThinningSettings(*self.region_geometry(), self.keep, self.seed)

    def draws(self, events: Events, seeds: Sequence[int]) -> list[Events]:
        """The outputs of this control with each of ``seeds`` in place of ``self.seed``.

        Equal to ``[replace(self, seed=s).kernel(events) for s in seeds]``, with the
        downsampling and the digest of the recording done once
        (``transforms.functional.thinning.thinning_draws``).
        """
        return thinning_draws(events, self.settings, seeds)
