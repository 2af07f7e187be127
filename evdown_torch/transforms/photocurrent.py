"""PhotocurrentPooling: the paper's events-to-video-to-events downscaler, with a session."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

from evdown_torch.transforms._base import Downscaler, Session
from evdown_torch.transforms.functional.photocurrent.method import (
    PHOTOCURRENT_EVENTS,
    PHOTOCURRENT_FRAMES,
)
from evdown_torch.transforms.functional.photocurrent.settings import PhotocurrentSettings
from evdown_torch.transforms.functional.protocol import Method


@dataclass(frozen=True)
class PhotocurrentPooling(Downscaler):
    """Photocurrent pooling (docs/semantics.md, method 7): what a physically larger pixel would see.

    Each input pixel's log intensity is ``contrast * L_p`` (``L_p``: its integer level, ON +1,
    OFF -1; every pixel starts at intensity 1). A region's photocurrent is the mean of its
    pixels' intensities, ``I_r = mean(exp(contrast * L_p))``, and the output pixel is a DVS
    pixel of contrast ``threshold`` watching ``log I_r``.

    *Events mode* (``fps=None``, the default): ``I_r`` changes only at input events, so output
    events take the triggering event's ``t``; causal, with a streaming :meth:`session` (the
    frames mode has one too, which emits a frame's events once the frame is complete).
    *Frames mode* (``fps`` set): the paper's literal pipeline. Intensity frames at
    ``t_start + k / fps`` (optionally high-pass filtered with ``cutoff_hz``), area-averaged
    in linear intensity, and events between consecutive low-resolution frames by the reference
    rule on the log intensity interpolated linearly in time, at exact crossing times.

    Float64 throughout; a ``log I_r`` within ``1e-9 * threshold`` of a level is on it. With
    ``factor=1`` and ``threshold == contrast`` the events mode returns its input; as
    ``contrast -> 0`` with ``threshold = contrast * k`` it tends to ``EventCount(k)``.

    Args:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
        contrast: the input camera's contrast threshold in log units, in [1e-6, 50].
        threshold: the output pixel's contrast threshold in log units, in [1e-6, 1e6]
            (default: ``contrast``, a camera of the same kind). The budget setting.
        fps: frames per second of the frames mode, or ``None`` for the events mode.
        cutoff_hz: high-pass leak of the frames mode in Hz (each event's log contribution
            decays as ``exp(-2 pi cutoff_hz dt)``, Scheerlinck et al. 2018), >= 0; 0 is no
            leak. With a leak, every frame of every region is computed (cost: frames x sensor
            area, in bounded chunks); a call whose frames times the sensor's pixels exceed
            the output limit (:func:`~evdown_torch.max_output_events`) is refused, naming the
            frame count.
        time_unit: seconds per timestamp unit, through which ``fps`` and ``cutoff_hz`` (per
            second) become per timestamp unit: ``None`` (the default) is 1e-6, microseconds
            as Tonic's datasets; 1.0 for float seconds (as some tools store N-Caltech101).
            Only the frames mode has rates: the events mode refuses a ``time_unit``. See
            :func:`~evdown_torch.checks.check_time_unit`. Stored as given (a name becomes
            seconds; ``None`` stays ``None``); :attr:`settings` holds the one in use.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 10, 1], [1, 0, 20, 1], [1, 0, 30, 0]])
        >>> PhotocurrentPooling((2, 1, 2), factor=(2, 1), contrast=0.5)(ev).tolist()
        [[0, 0, 20, 1]]
    """

    contrast: float = 0.2
    threshold: float | None = None
    fps: float | None = None
    cutoff_hz: float = 0.0
    time_unit: float | None = None

    #: The setting :func:`calibrate` searches to meet an event budget.
    budget_setting = "threshold"
    name = "photocurrent"
    #: A ``time_unit`` left out stays ``None``, so a copy without ``fps`` stays valid.
    none_stays_none = ("time_unit",)
    #: The events mode's kernels; :attr:`kernels` binds the frames mode's when ``fps`` is set.
    method = PHOTOCURRENT_EVENTS

    @cached_property
    def settings(self) -> PhotocurrentSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return PhotocurrentSettings(*self.region_geometry(), self.contrast, self.threshold,
                                    self.fps, self.cutoff_hz, self.time_unit)

    @property
    def kernels(self) -> Method[PhotocurrentSettings, Any]:
        """The events mode's bundle, or the frames mode's when ``fps`` is set."""
        return PHOTOCURRENT_EVENTS if self.fps is None else PHOTOCURRENT_FRAMES

    def algorithmic_delay(self) -> float:
        """0 in the events mode; in the frames mode one frame, ``1 / fps`` in stream time."""
        fps, time_unit = self.settings.fps, self.settings.time_unit
        if fps is None or time_unit is None:
            return 0.0
        return 1.0 / (fps * time_unit)

    def session(self) -> Session:
        """Start a streaming session over consecutive chunks of one stream (both modes).

        The common :class:`~evdown_torch.transforms._base.Session`: ``session(chunk)``,
        ``flush()`` and ``reset()``. The events mode is causal (``flush()`` returns nothing);
        the frames mode returns a chunk's events once their frame is complete, and ``flush()``
        the rest. Either way, the chunks' outputs and the flush concatenated equal one call on
        the whole stream.

        Example:
            >>> import torch
            >>> ev = torch.tensor([[0, 0, 10, 1], [1, 0, 20, 1], [1, 0, 30, 0]])
            >>> session = PhotocurrentPooling((2, 1, 2), factor=(2, 1), contrast=0.5).session()
            >>> [session(chunk).tolist() for chunk in (ev[:1], ev[1:1], ev[1:])]
            [[], [], [[0, 0, 20, 1]]]
        """
        return super().session()
