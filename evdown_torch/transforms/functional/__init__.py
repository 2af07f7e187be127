"""Pure, keyword-only, device-agnostic kernels on :class:`~evdown_torch.events.Events`."""

from evdown_torch.transforms.functional.downsample import downsample
from evdown_torch.transforms.functional.event_count import event_count
from evdown_torch.transforms.functional.funnelling import event_funnelling

__all__ = ["downsample", "event_count", "event_funnelling"]
