"""The thinning control: Downsample, then keep each event at random, seeded by the recording."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, NoReturn

import torch

from evdown_torch.checks import check_non_negative_int, check_unit_interval
from evdown_torch.events import Events
from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.functional.downsample import downsample
from evdown_torch.transforms.functional.draws import content_digest, mixed_seed, recording_seed

__all__ = ["ThinnedDownsample", "recording_seed"]


@dataclass(frozen=True)
class ThinnedDownsample(Downscaler):
    """Downsample, then keep each output event independently with probability ``keep``.

    The *thinning control* of the evaluation (docs/semantics.md, "Event budget"): it spends an
    event budget with no method at all, every kept event at its downsampled place and time.
    The random draws are seeded by the recording itself (:func:`recording_seed` of the input
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

    budget_setting: ClassVar[str | None] = "keep"

    keep: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "keep", check_unit_interval("keep", self.keep))
        check_non_negative_int("seed", self.seed)

    def session(self) -> NoReturn:
        """Not available: the draws are seeded by the whole recording, unknown before its end.

        Raises:
            NotImplementedError: always.
        """
        raise NotImplementedError(
            "ThinnedDownsample has no streaming session: its random draws are seeded by the "
            "whole recording, which a stream only knows at its end"
        )

    def kernel(self, events: Events) -> Events:
        """Downsample ``events`` and keep a seeded random subset."""
        return self.draws(events, (self.seed,))[0]

    def draws(self, events: Events, seeds: Sequence[int]) -> list[Events]:
        """The outputs of this control with each of ``seeds`` in place of ``self.seed``.

        Equal to ``[replace(self, seed=s).kernel(events) for s in seeds]``, with the
        downsampling and the digest of the recording done once (the trade study draws one
        thinning per training seed).
        """
        out = downsample(events, factor=self.factor_xy)
        if self.keep >= 1.0 or out.num_events == 0:
            return [out] * len(seeds)
        content = content_digest(events)
        kept = []
        for seed in seeds:
            check_non_negative_int("seed", seed)
            generator = torch.Generator().manual_seed(mixed_seed(content, seed))
            draws = torch.rand(out.num_events, generator=generator, dtype=torch.float64)
            kept.append(out.select((draws < self.keep).to(out.device)))
        return kept
