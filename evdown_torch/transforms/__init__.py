"""Downscaling transforms, usable alone or inside ``tonic.transforms.Compose``."""

from evdown_torch.transforms._base import Chain, Downscaler, Session, Streaming
from evdown_torch.transforms.downsample import Downsample, EventFunnelling
from evdown_torch.transforms.estimation import CubicEstimation, LinearEstimation
from evdown_torch.transforms.event_count import EventCount, EventCountSession
from evdown_torch.transforms.lif import LIFPooling, calibrate_weight
from evdown_torch.transforms.photocurrent import PhotocurrentPooling, PhotocurrentSession
from evdown_torch.transforms.temporal import TemporalFunnelling

__all__ = [
    "Chain",
    "CubicEstimation",
    "Downscaler",
    "Downsample",
    "EventCount",
    "EventCountSession",
    "EventFunnelling",
    "LIFPooling",
    "LinearEstimation",
    "PhotocurrentPooling",
    "PhotocurrentSession",
    "Session",
    "Streaming",
    "TemporalFunnelling",
    "calibrate_weight",
]
