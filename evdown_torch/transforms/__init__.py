"""Downscaling transforms, usable alone or inside ``tonic.transforms.Compose``."""

from evdown_torch.transforms._base import Chain, Downscaler, Method, Session, Streaming
from evdown_torch.transforms.calibrate import BudgetTarget, calibrate
from evdown_torch.transforms.downsample import Downsample, EventFunnelling
from evdown_torch.transforms.estimation import CubicEstimation, LinearEstimation
from evdown_torch.transforms.event_count import EventCount, EventCountSession
from evdown_torch.transforms.lif import LIFPooling, calibrate_weight
from evdown_torch.transforms.photocurrent import PhotocurrentPooling, PhotocurrentSession
from evdown_torch.transforms.subsampling import DensitySubsampling, PoissonSubsampling
from evdown_torch.transforms.temporal import TemporalFunnelling
from evdown_torch.transforms.thinning import ThinnedDownsample
from evdown_torch.transforms.tonic_peers import TonicDecimation, TonicRefractoryPeriod

__all__ = [
    "BudgetTarget",
    "Chain",
    "CubicEstimation",
    "DensitySubsampling",
    "Downscaler",
    "Downsample",
    "EventCount",
    "EventCountSession",
    "EventFunnelling",
    "LIFPooling",
    "LinearEstimation",
    "Method",
    "PhotocurrentPooling",
    "PhotocurrentSession",
    "PoissonSubsampling",
    "Session",
    "Streaming",
    "TemporalFunnelling",
    "ThinnedDownsample",
    "TonicDecimation",
    "TonicRefractoryPeriod",
    "calibrate",
    "calibrate_weight",
]
