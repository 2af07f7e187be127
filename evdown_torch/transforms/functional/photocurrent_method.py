"""PhotocurrentPooling as a method: its settings and its three kernels, in both modes.

The events mode's kernels are in :mod:`.photocurrent`, the frames mode's in
:mod:`.photocurrent_frames`; here are the settings both share (checked once) and the
``init_state`` / ``step`` / ``finish`` kernels that pick the mode from them.
"""

from __future__ import annotations

from dataclasses import dataclass

from evdown_torch.checks import (
    DEFAULT_TIME_UNIT,
    check_non_negative_float,
    check_positive_float,
    check_time_unit,
)
from evdown_torch.events import Events
from evdown_torch.transforms.functional.photocurrent import (
    PhotocurrentState,
    check_contrast_range,
    initial_state,
    photocurrent_events,
)
from evdown_torch.transforms.functional.photocurrent_frames import (
    FrameClock,
    FramesState,
    frames_stream,
    fresh_frames_state,
    photocurrent_frames,
)
from evdown_torch.transforms.functional.settings import RegionSettings

__all__ = [
    "PhotocurrentSettings",
    "photocurrent_finish",
    "photocurrent_init",
    "photocurrent_step",
    "photocurrent_whole",
]


@dataclass(frozen=True)
class PhotocurrentSettings(RegionSettings):
    """Photocurrent pooling's settings, checked and normalised once.

    Attributes:
        contrast: the input camera's contrast threshold in log units, in [1e-6, 50].
        threshold: the output pixel's contrast threshold in log units (``None``:
            ``contrast``; stored as a float).
        fps: frames per second of the frames mode, or ``None`` for the events mode.
        cutoff_hz: the frames mode's high-pass leak in Hz, >= 0.
        time_unit: seconds per timestamp unit for ``fps`` and ``cutoff_hz`` (frames mode
            only; stored as 1e-6 when not given there).
    """

    contrast: float = 0.2
    threshold: float | None = None
    fps: float | None = None
    cutoff_hz: float = 0.0
    time_unit: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        contrast = check_positive_float("contrast", self.contrast)
        threshold = contrast if self.threshold is None else self.threshold
        threshold = check_positive_float("threshold", threshold)
        check_contrast_range(contrast, threshold)
        object.__setattr__(self, "contrast", contrast)
        object.__setattr__(self, "threshold", threshold)
        cutoff = check_non_negative_float("cutoff_hz", self.cutoff_hz)
        object.__setattr__(self, "cutoff_hz", cutoff)
        if self.fps is None:
            if cutoff > 0:
                raise ValueError(f"cutoff_hz={cutoff!r} needs the frames mode: set fps")
            if self.time_unit is not None:
                raise ValueError(
                    f"time_unit={self.time_unit!r} converts the frames mode's fps and cutoff_hz; "
                    "the events mode (fps=None) has no rate to convert: set fps or leave "
                    "time_unit out"
                )
            return
        fps = check_positive_float("fps", self.fps)
        time_unit = check_time_unit(
            DEFAULT_TIME_UNIT if self.time_unit is None else self.time_unit
        )
        FrameClock.make(fps, 0, time_unit)
        object.__setattr__(self, "fps", fps)
        object.__setattr__(self, "time_unit", time_unit)


State = PhotocurrentState | FramesState


def photocurrent_init(settings: PhotocurrentSettings, events: Events) -> State:
    """``init_state``: every pixel at intensity 1 and every region at ``q = 0``; in the
    frames mode, frame 0 at the first chunk's first timestamp."""
    if settings.fps is None:
        return initial_state(settings.sensor_size, settings.factor, events.device)
    return fresh_frames_state(events, settings.sensor_size, settings.factor)


def photocurrent_step(
    events: Events, state: State, settings: PhotocurrentSettings
) -> tuple[Events, State]:
    """``step`` on one time-sorted chunk. Events mode: causal, every output is decided by its
    chunk. Frames mode: the events of every frame complete so far (a frame is complete once a
    later event has been seen; with a leak, in whole chunks of frames)."""
    if settings.fps is None:
        return photocurrent_events(
            events, sensor_size=settings.sensor_size, factor=settings.factor,
            contrast=settings.contrast, threshold=settings.threshold,  # type: ignore[arg-type]
            state=state,  # type: ignore[arg-type]
        )
    return _frames(events, state, settings, final=False)  # type: ignore[arg-type,return-value]


def photocurrent_finish(state: State, settings: PhotocurrentSettings) -> Events | None:
    """``finish``: the frames mode's open frames, the last clipped to the stream's end (the
    events mode leaves nothing: it is causal)."""
    if settings.fps is None:
        return None
    empty = Events(*(column[:0] for column in state.pending))  # type: ignore[union-attr]
    return _frames(empty, state, settings, final=True)[0]  # type: ignore[arg-type]


def photocurrent_whole(events: Events, settings: PhotocurrentSettings) -> Events:
    """The whole stream (any order) in one call, in the settings' mode."""
    if settings.fps is None:
        out, _ = photocurrent_events(
            events, sensor_size=settings.sensor_size, factor=settings.factor,
            contrast=settings.contrast, threshold=settings.threshold,  # type: ignore[arg-type]
        )
        return out
    return photocurrent_frames(
        events, sensor_size=settings.sensor_size, factor=settings.factor,
        contrast=settings.contrast, threshold=settings.threshold,  # type: ignore[arg-type]
        fps=settings.fps, cutoff_hz=settings.cutoff_hz,
        time_unit=settings.time_unit,  # type: ignore[arg-type]
    )


def _frames(
    events: Events, state: FramesState, settings: PhotocurrentSettings, *, final: bool
) -> tuple[Events, FramesState | None]:
    return frames_stream(
        events, sensor_size=settings.sensor_size, factor=settings.factor,
        contrast=settings.contrast, threshold=settings.threshold,  # type: ignore[arg-type]
        fps=settings.fps, cutoff_hz=settings.cutoff_hz,  # type: ignore[arg-type]
        time_unit=settings.time_unit, state=state, final=final,  # type: ignore[arg-type]
    )
