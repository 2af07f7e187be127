"""Pure, device-agnostic kernels on :class:`~evdown_torch.events.Events`.

Each method is a frozen settings dataclass, checked once (:class:`RegionSettings`,
:class:`ThresholdSettings`, :class:`EstimationSettings`, :class:`PhotocurrentSettings`,
:class:`TemporalSettings`, :class:`RateLimitSettings`, :class:`LIFSettings` inside
:class:`LIFPoolingSettings`, :class:`DensitySettings`, :class:`PoissonSettings`), and three
kernels ``init_state``, ``step`` and ``finish`` on them
(:class:`~evdown_torch.transforms.Method`). The whole-stream functions below take the
settings as keywords, for direct use.
"""

from evdown_torch.transforms.functional.density import DensitySettings, density_subsampling
from evdown_torch.transforms.functional.downsample import downsample
from evdown_torch.transforms.functional.estimation.method import (
    cubic_estimation,
    linear_estimation,
)
from evdown_torch.transforms.functional.estimation.settings import EstimationSettings
from evdown_torch.transforms.functional.event_count import event_count
from evdown_torch.transforms.functional.funnelling import event_funnelling
from evdown_torch.transforms.functional.lif.pooling import lif_pooling
from evdown_torch.transforms.functional.lif.settings import LIFPoolingSettings, LIFSettings
from evdown_torch.transforms.functional.photocurrent.events_mode import photocurrent_events
from evdown_torch.transforms.functional.photocurrent.frames_mode import photocurrent_frames
from evdown_torch.transforms.functional.photocurrent.settings import PhotocurrentSettings
from evdown_torch.transforms.functional.poisson import PoissonSettings, poisson_subsampling
from evdown_torch.transforms.functional.rate_limit import RateLimitSettings, limit_rate
from evdown_torch.transforms.functional.settings import RegionSettings, ThresholdSettings
from evdown_torch.transforms.functional.temporal import TemporalSettings, temporal_funnelling

__all__ = [
    "DensitySettings",
    "EstimationSettings",
    "LIFPoolingSettings",
    "LIFSettings",
    "PhotocurrentSettings",
    "PoissonSettings",
    "RateLimitSettings",
    "RegionSettings",
    "TemporalSettings",
    "ThresholdSettings",
    "cubic_estimation",
    "density_subsampling",
    "downsample",
    "event_count",
    "event_funnelling",
    "lif_pooling",
    "limit_rate",
    "linear_estimation",
    "photocurrent_events",
    "photocurrent_frames",
    "poisson_subsampling",
    "temporal_funnelling",
]
