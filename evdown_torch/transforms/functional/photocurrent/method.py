"""PhotocurrentPooling's two methods: the events mode's and the frames mode's bundles.

The events mode's kernels are in :mod:`.events_mode`, the frames mode's in
:mod:`.frames_mode`, the settings both share in :mod:`.settings`. Here are the two bundles,
:data:`PHOTOCURRENT_EVENTS` and :data:`PHOTOCURRENT_FRAMES`, each with its
``init_state`` / ``step`` / ``finish`` kernels; the transform binds one of them from its
``fps``.
"""

from __future__ import annotations

from evdown_torch.collate import EventBatch
from evdown_torch.events import Events, sort_by_time
from evdown_torch.transforms.functional.batch import Stacked, run_stacked
from evdown_torch.transforms.functional.photocurrent.events_mode import (
    initial_state,
    photocurrent_events,
    photocurrent_sorted,
)
from evdown_torch.transforms.functional.photocurrent.frames_mode import (
    FramesState,
    frames_stream,
    fresh_frames_state,
)
from evdown_torch.transforms.functional.photocurrent.settings import (
    PhotocurrentSettings,
    PhotocurrentState,
)
from evdown_torch.transforms.functional.protocol import Method

__all__ = [
    "PHOTOCURRENT_EVENTS",
    "PHOTOCURRENT_FRAMES",
    "photocurrent_events_init",
    "photocurrent_events_stacked",
    "photocurrent_events_step",
    "photocurrent_events_whole",
    "photocurrent_frames_finish",
    "photocurrent_frames_init",
    "photocurrent_frames_step",
    "photocurrent_frames_whole",
]


def photocurrent_events_init(settings: PhotocurrentSettings, events: Events) -> PhotocurrentState:
    """Events mode's ``init_state``: every pixel at intensity 1 and every region at ``q = 0``."""
    return initial_state(settings.sensor_size, settings.factor, events.device)


def photocurrent_events_step(
    events: Events, state: PhotocurrentState, settings: PhotocurrentSettings
) -> tuple[Events, PhotocurrentState]:
    """Events mode's ``step`` on one time-sorted chunk: causal, every output decided by it."""
    return photocurrent_sorted(events, settings.sensor_size, settings.factor, settings.contrast,
                               settings.output_threshold, state)


def photocurrent_events_whole(events: Events, settings: PhotocurrentSettings) -> Events:
    """Events mode on the whole stream (any order) in one call."""
    return photocurrent_events(
        events, sensor_size=settings.sensor_size, factor=settings.factor,
        contrast=settings.contrast, threshold=settings.output_threshold,
    )


def photocurrent_events_stacked(batch: EventBatch, settings: PhotocurrentSettings) -> EventBatch:
    """Events mode: the kernel once on the stacked batch, one block of regions per recording."""

    def kernel(stacked: Stacked) -> Events:
        out, _ = photocurrent_sorted(
            sort_by_time(stacked.events), settings.sensor_size, settings.factor,
            settings.contrast, settings.output_threshold, None, stacked.recordings,
        )
        return out

    return run_stacked(batch, kernel, sensor_size=settings.sensor_size, factor=settings.factor)


def photocurrent_frames_init(settings: PhotocurrentSettings, events: Events) -> FramesState:
    """Frames mode's ``init_state``: frame 0 at the first chunk's first timestamp."""
    return fresh_frames_state(events, settings.sensor_size, settings.factor)


def photocurrent_frames_step(
    events: Events, state: FramesState | None, settings: PhotocurrentSettings
) -> tuple[Events, FramesState | None]:
    """Frames mode's ``step``: the events of every frame complete so far.

    A frame is complete once a later event has been seen; with a leak, in whole chunks of
    frames.
    """
    return frames_stream(events, state, settings, final=False)


def photocurrent_frames_finish(
    state: FramesState | None, settings: PhotocurrentSettings
) -> Events | None:
    """Frames mode's ``finish``: the open frames, the last clipped to the stream's end."""
    if state is None:
        return None
    return frames_stream(state.pending.part(0, 0), state, settings, final=True)[0]


def photocurrent_frames_whole(events: Events, settings: PhotocurrentSettings) -> Events:
    """Frames mode on the whole stream (any order) in one call."""
    return frames_stream(events, None, settings, final=True)[0]


#: PhotocurrentPooling's events mode (``fps=None``): causal, batched.
PHOTOCURRENT_EVENTS: Method[PhotocurrentSettings, PhotocurrentState] = Method(
    photocurrent_events_init, photocurrent_events_step,
    whole=photocurrent_events_whole, stacked=photocurrent_events_stacked,
)

#: PhotocurrentPooling's frames mode (``fps`` set): the paper's literal pipeline, one recording
#: at a time.
PHOTOCURRENT_FRAMES: Method[PhotocurrentSettings, FramesState | None] = Method(
    photocurrent_frames_init, photocurrent_frames_step, photocurrent_frames_finish,
    whole=photocurrent_frames_whole,
)
