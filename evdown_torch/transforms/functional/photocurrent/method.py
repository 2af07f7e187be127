"""PhotocurrentPooling as a method: its settings and its three kernels, in both modes.

The events mode's kernels are in :mod:`.events_mode`, the frames mode's in
:mod:`.frames_mode`, the settings both share in :mod:`.settings`; here
are the ``init_state`` / ``step`` / ``finish`` kernels that pick the mode from the settings.
"""

from __future__ import annotations

from evdown_torch.events import Events
from evdown_torch.transforms.functional.photocurrent.events_mode import (
    PhotocurrentState,
    initial_state,
    photocurrent_events,
    photocurrent_sorted,
)
from evdown_torch.transforms.functional.photocurrent.frames_mode import (
    FramesState,
    frames_stream,
    fresh_frames_state,
)
from evdown_torch.transforms.functional.photocurrent.settings import PhotocurrentSettings

__all__ = [
    "photocurrent_finish",
    "photocurrent_init",
    "photocurrent_step",
    "photocurrent_whole",
]


State = PhotocurrentState | FramesState


def photocurrent_init(settings: PhotocurrentSettings, events: Events) -> State:
    """``init_state``: every pixel at intensity 1 and every region at ``q = 0``.

    In the frames mode, frame 0 is at the first chunk's first timestamp.
    """
    if settings.fps is None:
        return initial_state(settings.sensor_size, settings.factor, events.device)
    return fresh_frames_state(events, settings.sensor_size, settings.factor)


def photocurrent_step(
    events: Events, state: State, settings: PhotocurrentSettings
) -> tuple[Events, State]:
    """``step`` on one time-sorted chunk.

    Events mode: causal, every output is decided by its chunk. Frames mode: the events of
    every frame complete so far (a frame is complete once a later event has been seen; with a
    leak, in whole chunks of frames).
    """
    if settings.fps is None:
        return photocurrent_sorted(
            events, settings.sensor_size, settings.factor, settings.contrast,
            settings.threshold, state,  # type: ignore[arg-type]
        )
    return frames_stream(events, state, settings, final=False)  # type: ignore[arg-type,return-value]


def photocurrent_finish(state: State, settings: PhotocurrentSettings) -> Events | None:
    """``finish``: the frames mode's open frames, the last clipped to the stream's end.

    The events mode leaves nothing (it is causal).
    """
    if settings.fps is None:
        return None
    empty = state.pending.part(0, 0)  # type: ignore[union-attr]
    return frames_stream(empty, state, settings, final=True)[0]  # type: ignore[arg-type]


def photocurrent_whole(events: Events, settings: PhotocurrentSettings) -> Events:
    """The whole stream (any order) in one call, in the settings' mode."""
    if settings.fps is None:
        out, _ = photocurrent_events(
            events, sensor_size=settings.sensor_size, factor=settings.factor,
            contrast=settings.contrast, threshold=settings.threshold,  # type: ignore[arg-type]
        )
        return out
    return frames_stream(events, None, settings, final=True)[0]
