"""evdown_torch: exact, vectorised downscaling of event-camera (DVS) streams in PyTorch."""

from evdown_torch.checks import max_output_events, output_limit, set_max_output_events
from evdown_torch.events import Events, from_events, to_events
from evdown_torch.transforms import (
    Chain,
    CubicEstimation,
    DensitySubsampling,
    Downsample,
    EventCount,
    EventFunnelling,
    LIFPooling,
    LinearEstimation,
    PhotocurrentPooling,
    PoissonSubsampling,
    RateLimiter,
    TemporalFunnelling,
)
from evdown_torch.transforms.functional.compiled import eager_kernels, kernel_path
from evdown_torch.transforms.functional.compiled.scratch import release_scratch

__version__ = "0.1.0"

__all__ = [
    "Chain",
    "CubicEstimation",
    "DensitySubsampling",
    "Downsample",
    "EventCount",
    "EventFunnelling",
    "Events",
    "LIFPooling",
    "LinearEstimation",
    "PhotocurrentPooling",
    "PoissonSubsampling",
    "RateLimiter",
    "TemporalFunnelling",
    "__version__",
    "eager_kernels",
    "from_events",
    "kernel_path",
    "max_output_events",
    "output_limit",
    "release_scratch",
    "set_max_output_events",
    "to_events",
]
