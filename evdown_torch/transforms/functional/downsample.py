"""Downsample kernel: divide coordinates, keep every event."""

from __future__ import annotations

from evdown_torch._tensors import region_of, sort_by_time
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = ["downsample", "downsample_init", "downsample_step", "downsample_whole"]


def downsample(events: Events, *, factor: tuple[int, int]) -> Events:
    """Map every event to its region ``(x // fx, y // fy)``; no event is dropped.

    Args:
        events: ``N`` events (any order).
        factor: ``(fx, fy)``, positive integers.

    Returns:
        ``N`` events in stable time order, with coordinates in the output sensor.

    Example:
        >>> ev = Events.from_columns([0, 3, 5], [1, 1, 7], [30, 10, 20], [1, 0, 1])
        >>> out = downsample(ev, factor=(2, 4))
        >>> out.x.tolist(), out.y.tolist(), out.t.tolist()
        ([1, 2, 0], [0, 1, 0], [10, 20, 30])
    """
    events = sort_by_time(events)
    x, y = region_of(events, factor)
    return Events(x, y, events.t.clone(), events.p.clone())


def downsample_init(settings: RegionSettings, events: Events) -> None:
    """Downsample's ``init_state``: it keeps no state (every event is decided at once)."""
    return None


def downsample_step(
    events: Events, state: None, settings: RegionSettings
) -> tuple[Events, None]:
    """Downsample's ``step``: one time-sorted chunk, every event decided by it.

    On the CPU, the compiled loop of :mod:`.compiled.downsample` unless the eager kernels are
    forced (:func:`.compiled.use_compiled`).
    """
    if use_compiled(events.t):
        from evdown_torch.transforms.functional.compiled import downsample as compiled

        return compiled.downsample_step(events, settings), None
    x, y = region_of(events, settings.factor)
    return Events(x, y, events.t.clone(), events.p.clone()), None


def downsample_whole(events: Events, settings: RegionSettings) -> Events:
    """Downsample's whole-stream kernel (events in any order): :func:`downsample`."""
    if use_compiled(events.t):
        return downsample_step(sort_by_time(events), None, settings)[0]
    return downsample(events, factor=settings.factor)
