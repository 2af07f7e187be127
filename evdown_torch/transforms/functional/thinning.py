"""The thinning control's kernel: Downsample, then keep each event at random.

The draws are seeded by the recording itself (its content digest) and a seed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from evdown_torch.checks import check_non_negative_int, check_output_count, check_unit_interval
from evdown_torch.events import Events
from evdown_torch.transforms.functional.downsample import downsample
from evdown_torch.transforms.functional.draws import content_digest, mixed_seed, recording_seed
from evdown_torch.transforms.functional.protocol import Method
from evdown_torch.transforms.functional.settings import RegionSettings

#: How the thinning control's output gets under the output limit.
THINNED_FEWER = "a smaller keep gives fewer events"

__all__ = ["THINNING", "ThinningSettings", "recording_seed", "thinning_draws", "thinning_whole"]


@dataclass(frozen=True)
class ThinningSettings(RegionSettings):
    """The thinning control's settings.

    Attributes:
        keep: probability of keeping each event, in ``[0, 1]``.
        seed: non-negative integer mixed into every recording's seed.
    """

    keep: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "keep", check_unit_interval("keep", self.keep))
        check_non_negative_int("seed", self.seed)


def thinning_draws(
    events: Events, settings: ThinningSettings, seeds: Sequence[int]
) -> list[Events]:
    """The control's output with each of ``seeds`` in place of ``settings.seed``.

    The downsampling and the digest of the recording are done once (the trade study draws one
    thinning per training seed).
    """
    out = downsample(events, factor=settings.factor)
    if settings.keep >= 1.0 or out.num_events == 0:
        check_output_count(out.num_events, fewer=THINNED_FEWER)
        return [out] * len(seeds)
    content = content_digest(events)
    kept = []
    for seed in seeds:
        check_non_negative_int("seed", seed)
        generator = torch.Generator().manual_seed(mixed_seed(content, seed))
        draws = torch.rand(out.num_events, generator=generator, dtype=torch.float64)
        kept.append(out.select((draws < settings.keep).to(out.device)))
        check_output_count(kept[-1].num_events, fewer=THINNED_FEWER)  # at most the input
    return kept


def thinning_whole(events: Events, settings: ThinningSettings) -> Events:
    """The whole recording: downsampled, then a subset seeded by the recording and the seed."""
    return thinning_draws(events, settings, (settings.seed,))[0]


#: The thinning control's kernels: the whole recording only (its draws are seeded by the
#: whole recording, which a stream only knows at its end).
THINNING: Method[ThinningSettings, None] = Method(
    whole=thinning_whole,
    no_stream="its random draws are seeded by the whole recording, which a stream only knows "
    "at its end",
)
