"""Downsample kernel: divide coordinates, keep every event."""

from __future__ import annotations

from evdown_torch._regions import region_of
from evdown_torch.checks import check_output_count
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events, sort_by_time
from evdown_torch.transforms.functional.batch import Stacked, run_stacked, sorted_within
from evdown_torch.transforms.functional.compiled import use_compiled
from evdown_torch.transforms.functional.protocol import Method
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = [
    "DOWNSAMPLE",
    "downsample",
    "downsample_init",
    "downsample_stacked",
    "downsample_step",
    "downsample_whole",
    "to_regions",
]

#: How Downsample's output gets under the output limit: it keeps every event it is given.
KEEPS_EVERY_EVENT = "Downsample keeps every input event: give it fewer events per call"


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
    return to_regions(sort_by_time(events), factor)


def to_regions(events: Events, factor: tuple[int, int]) -> Events:
    """Every event moved to its region ``(x // fx, y // fy)``, in the given order.

    What Downsample does to events in time order, and what every method that keeps input
    events (the subsamplers, Tonic's filters) does to those it keeps. Every column of the
    result is a new tensor.

    Example:
        >>> to_regions(Events.from_columns([0, 3], [5, 1], [7, 2], [1, 0]), (2, 2)).x.tolist()
        [0, 1]
    """
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
    check_output_count(events.num_events, fewer=KEEPS_EVERY_EVENT)
    if use_compiled(events.t):
        from evdown_torch.transforms.functional.compiled import downsample as compiled

        return compiled.downsample_step(events, settings), None
    return to_regions(events, settings.factor), None


def downsample_whole(events: Events, settings: RegionSettings) -> Events:
    """Downsample's whole-stream kernel (events in any order): :func:`downsample`."""
    check_output_count(events.num_events, fewer=KEEPS_EVERY_EVENT)
    if use_compiled(events.t):
        return downsample_step(sort_by_time(events), None, settings)[0]
    return downsample(events, factor=settings.factor)


def downsample_stacked(batch: EventBatch, settings: RegionSettings) -> EventBatch:
    """A batch in one call (events do not interact).

    Recordings each in time order need only the division; others go through
    :func:`downsample_whole` once on the stacked batch.
    """
    events = batch.events
    if sorted_within(events.t, batch.lengths):
        check_output_count(events.num_events, fewer=KEEPS_EVERY_EVENT)
        return EventBatch(to_regions(events, settings.factor), batch.lengths)

    def kernel(stacked: Stacked) -> Events:
        return downsample_whole(stacked.events, settings)

    return run_stacked(batch, kernel, sensor_size=settings.sensor_size, factor=settings.factor)


#: Downsample's kernels (:class:`~evdown_torch.Downsample`).
DOWNSAMPLE: Method[RegionSettings, None] = Method(
    downsample_init, downsample_step, whole=downsample_whole, stacked=downsample_stacked
)
