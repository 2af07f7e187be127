"""Downscaling transforms, usable alone or inside ``tonic.transforms.Compose``.

With them: the rate limiter (:class:`RateLimiter`), the event-budget calibration
(:func:`calibrate`, :class:`BudgetTarget`) and the window rates of a stream
(:func:`window_rates`).
"""

from evdown_torch.transforms._base import (
    Chain,
    Downscaler,
    Session,
    Streaming,
    ThresholdDownscaler,
)
from evdown_torch.transforms.calibrate import BudgetTarget, calibrate
from evdown_torch.transforms.downsample import Downsample, EventFunnelling
from evdown_torch.transforms.estimation import CubicEstimation, LinearEstimation
from evdown_torch.transforms.event_count import EventCount
from evdown_torch.transforms.functional.protocol import Method
from evdown_torch.transforms.lif import LIFPooling, calibrate_weight
from evdown_torch.transforms.photocurrent import PhotocurrentPooling
from evdown_torch.transforms.rate_limit import RateLimiter
from evdown_torch.transforms.subsampling import DensitySubsampling, PoissonSubsampling
from evdown_torch.transforms.temporal import TemporalFunnelling
from evdown_torch.transforms.thinning import ThinnedDownsample
from evdown_torch.transforms.tonic_peers import TonicDecimation, TonicRefractoryPeriod
from evdown_torch.transforms.window_rates import WindowRates, window_rates

__all__ = [
    "BudgetTarget",
    "Chain",
    "CubicEstimation",
    "DensitySubsampling",
    "Downscaler",
    "Downsample",
    "EventCount",
    "EventFunnelling",
    "LIFPooling",
    "LinearEstimation",
    "Method",
    "PhotocurrentPooling",
    "PoissonSubsampling",
    "RateLimiter",
    "Session",
    "Streaming",
    "TemporalFunnelling",
    "ThinnedDownsample",
    "ThresholdDownscaler",
    "TonicDecimation",
    "TonicRefractoryPeriod",
    "WindowRates",
    "calibrate",
    "calibrate_weight",
    "window_rates",
]
