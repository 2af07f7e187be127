"""evdown_torch: exact, vectorised downscaling of event-camera (DVS) streams in PyTorch."""

from evdown_torch.events import Events, from_events, to_events
from evdown_torch.transforms import Downsample, EventFunnelling, LIFPooling

__version__ = "0.1.0"

__all__ = [
    "Events",
    "Downsample",
    "EventFunnelling",
    "LIFPooling",
    "from_events",
    "to_events",
    "__version__",
]
