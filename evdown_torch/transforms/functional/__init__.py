"""Pure, device-agnostic kernels on :class:`~evdown_torch.events.Events`.

Settings are keyword arguments, except LIF pooling's, which travel as one checked
:class:`~evdown_torch.transforms.functional.lif_settings.LIFSettings`.
"""

from evdown_torch.transforms.functional.cubic import cubic_estimation
from evdown_torch.transforms.functional.downsample import downsample
from evdown_torch.transforms.functional.event_count import event_count
from evdown_torch.transforms.functional.funnelling import event_funnelling
from evdown_torch.transforms.functional.lif import lif_pooling
from evdown_torch.transforms.functional.lif_settings import LIFSettings
from evdown_torch.transforms.functional.linear import linear_estimation
from evdown_torch.transforms.functional.photocurrent import photocurrent_events
from evdown_torch.transforms.functional.photocurrent_frames import photocurrent_frames
from evdown_torch.transforms.functional.temporal import temporal_funnelling

__all__ = [
    "LIFSettings",
    "cubic_estimation",
    "downsample",
    "event_count",
    "event_funnelling",
    "lif_pooling",
    "linear_estimation",
    "photocurrent_events",
    "photocurrent_frames",
    "temporal_funnelling",
]
