"""Downscaling transforms, usable alone or inside ``tonic.transforms.Compose``."""

from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.downsample import Downsample, EventFunnelling
from evdown_torch.transforms.event_count import EventCount, EventCountSession
from evdown_torch.transforms.lif import LIFPooling, calibrate_weight

__all__ = [
    "Downscaler",
    "Downsample",
    "EventCount",
    "EventCountSession",
    "EventFunnelling",
    "LIFPooling",
    "calibrate_weight",
]
