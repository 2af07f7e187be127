"""What ``evdown show`` looks at: a recording (file or synthetic) and its downscaled versions.

Nothing here imports matplotlib. :func:`read_file` is the one place a file named on the command
line is read, so that other readers (AEDAT4) plug in there.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, cast

import numpy as np
import torch

from evdown_torch.checks import check_factor, check_sensor_size, output_size
from evdown_torch.events import Events, EventsLike, sort_by_time, to_events
from evdown_torch.io import read_microseconds
from evdown_torch.transforms import Downscaler
from evdown_torch.transforms.registry import METHODS, make_method

__all__ = ["Panel", "ShownRecording", "load_recording", "method_name", "panels"]

#: Sensor of synthetic recordings (DVS128 Gesture's).
SYNTHETIC_SENSOR = (128, 128, 2)

#: Default length of a synthetic recording, milliseconds.
SYNTHETIC_DURATION_MS = 2000.0


class Panel(NamedTuple):
    """One stream to show.

    Attributes:
        name: what it is (``"input"``, a method name, ``"ground truth"``).
        events: the events, sorted by ``t`` (microseconds).
        sensor_size: ``(W, H, P)`` the events live on.
    """

    name: str
    events: Events
    sensor_size: tuple[int, int, int]


@dataclass(frozen=True)
class ShownRecording:
    """A recording to show, and where it came from.

    Attributes:
        events: the events, sorted by ``t`` (microseconds).
        sensor_size: ``(W, H, P)``.
        name: where it came from (file name or ``synthetic:CLASS:SEED``).
        label: class of a synthetic gesture or an N-MNIST recording, else ``None``.
        seed: seed of a synthetic recording, else ``None``.
        duration_us: length of a synthetic recording, else ``None``.
    """

    events: Events
    sensor_size: tuple[int, int, int]
    name: str
    label: int | None = None
    seed: int | None = None
    duration_us: int | None = None

    def ground_truth(self, factor: int | tuple[int, int]) -> Panel | None:
        """The low-resolution ground truth of a synthetic recording (``None`` for a file).

        The same scene rendered on a sensor ``factor`` times smaller.
        """
        if self.label is None or self.seed is None or self.duration_us is None:
            return None
        from evdown_torch.synthetic import render_gesture

        fxy = check_factor(factor, self.sensor_size)
        low = render_gesture(self.label, self.seed, sensor_size=self.sensor_size,
                             duration_us=self.duration_us, factor=fxy)
        size = output_size(self.sensor_size, fxy)
        return Panel("ground truth", to_events(low, size)[0], size)


def _synthetic_label(text: str) -> int:
    from evdown_torch.synthetic import GESTURE_CLASSES

    def key(name: str) -> str:
        return "".join(c for c in name.lower() if c.isalnum())

    if text.isdigit():
        label = int(text)
        if label < len(GESTURE_CLASSES):
            return label
    else:
        for label, name in enumerate(GESTURE_CLASSES):
            if key(name) == key(text):
                return label
    raise ValueError(
        f"unknown synthetic class {text!r}; expected an index 0-{len(GESTURE_CLASSES) - 1} or "
        f"one of {', '.join(repr(n) for n in GESTURE_CLASSES)}"
    )


def load_recording(
    spec: str,
    *,
    sensor_size: tuple[int, int, int] | None = None,
    duration_ms: float | None = None,
    time_unit: str | None = None,
    columns: Any = None,
    root: str | None = None,
    split: str = "train",
) -> ShownRecording:
    """Read the recording named ``spec``.

    Args:
        spec: an event file that :func:`evdown_torch.io.read_events` reads (``.npy``, HDF5,
            AEDAT4, N-MNIST ``.bin``, Prophesee ``.raw``/``.dat``; ``t`` in microseconds),
            ``synthetic:CLASS[:SEED]`` (a gesture of :mod:`evdown_torch.synthetic`; ``CLASS``
            an index or a class name, case, spaces and underscores ignored; seed 0 by
            default), or ``nmnist:DIGIT[:N]`` (the ``N``-th recording, from 0 in file-name
            order, of digit ``DIGIT`` of the N-MNIST folder ``root``; 0 by default).
        root: the N-MNIST folder (:class:`~evdown_torch.data.sources.NMNISTSource`), for
            ``nmnist:`` only.
        split: ``"train"`` or ``"test"``, the N-MNIST split.
        sensor_size: ``(W, H, P)``; default: the synthetic sensor (128, 128, 2), or for a file
            its own, else the largest coordinates + 1.
        time_unit: the unit of a file's timestamps where the file states none (default
            microseconds); they are converted to microseconds.
        columns: the column order of a ``.npy`` file holding an ``(N, 4)`` array.
        duration_ms: length of a synthetic recording (default 2000 ms); for a file, only its
            first ``duration_ms`` are kept (default: all of it).

    Returns:
        The :class:`ShownRecording`.

    Raises:
        ValueError: for a missing or unreadable file, an unknown class or bad settings.

    Example:
        >>> rec = load_recording("synthetic:right_arm_cw:2", sensor_size=(32, 32, 2),
        ...                      duration_ms=200)
        >>> rec.label, rec.sensor_size, rec.name
        (3, (32, 32, 2), 'synthetic:3:2')
    """
    if duration_ms is not None and not (float(duration_ms) > 0):
        raise ValueError(f"duration must be a positive number of ms, got {duration_ms!r}")
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    if spec.startswith("synthetic:"):
        from evdown_torch.synthetic import render_gesture

        parts = spec.split(":")
        if len(parts) > 3 or not parts[1]:
            raise ValueError(f"a synthetic input looks like synthetic:CLASS[:SEED], got {spec!r}")
        label = _synthetic_label(parts[1])
        seed_text = parts[2] if len(parts) == 3 else "0"
        if not seed_text.isdigit():
            raise ValueError(f"the seed of {spec!r} must be a non-negative integer")
        seed = int(seed_text)
        size = sensor_size or SYNTHETIC_SENSOR
        duration_us = round(1000 * (duration_ms or SYNTHETIC_DURATION_MS))
        raw = render_gesture(label, seed, sensor_size=size, duration_us=duration_us)
        return ShownRecording(to_events(raw, size)[0], size, f"synthetic:{label}:{seed}",
                         label, seed, duration_us)
    digit = None
    if spec.startswith("nmnist:"):
        raw, sensor_size, digit, spec = _nmnist_recording(spec, root, split, sensor_size)
    else:
        if root is not None:
            raise ValueError(f"--root names the N-MNIST folder of an nmnist:DIGIT[:N] input, "
                             f"not of {spec!r}")
        raw, sensor_size = read_file(spec, sensor_size, time_unit=time_unit, columns=columns)
    events = sort_by_time(to_events(raw, sensor_size)[0])
    if duration_ms is not None and events.num_events:
        end = events.t[0] + duration_ms * 1000
        events = events.select(events.t < end)
    return ShownRecording(events, sensor_size, spec, digit)


def _nmnist_recording(
    spec: str, root: str | None, split: str, sensor_size: tuple[int, int, int] | None
) -> tuple[np.ndarray, tuple[int, int, int], int, str]:
    """``nmnist:DIGIT[:N]`` of the folder ``root``: ``(events, sensor, label, name)``."""
    from evdown_torch.data.sources import NMNISTSource

    parts = spec.split(":")
    if len(parts) > 3 or not all(part.isdigit() for part in parts[1:]) or int(parts[1]) > 9:
        raise ValueError(f"an N-MNIST input looks like nmnist:DIGIT[:N] (a digit 0-9, then "
                         f"which of its recordings, from 0), got {spec!r}")
    if root is None:
        raise ValueError(f"{spec} needs --root DIR, the N-MNIST folder (Train/<digit>/*.bin)")
    source = NMNISTSource(root, split=split)
    if sensor_size is not None and sensor_size != source.sensor_size:
        raise ValueError(f"N-MNIST's sensor is {source.sensor_size}; drop --sensor-size")
    digit, nth = int(parts[1]), int(parts[2]) if len(parts) == 3 else 0
    indices = [i for i, label in enumerate(source.labels) if label == digit]
    if nth >= len(indices):
        raise ValueError(f"{spec}: the {split} split has {len(indices)} recordings of digit "
                         f"{digit} (N from 0 to {len(indices) - 1})")
    events, label = source.load(indices[nth])
    return events, source.sensor_size, label, source.source_name(indices[nth])


def read_file(
    path: str,
    sensor_size: tuple[int, int, int] | None,
    *,
    time_unit: str | None = None,
    columns: Any = None,
) -> tuple[np.ndarray, tuple[int, int, int]]:
    """The one file reader of ``evdown show``.

    A structured event array with ``t`` in microseconds and its sensor size (the file's own,
    else ``sensor_size``, else guessed from the largest coordinates with a warning; see
    :func:`evdown_torch.io.read_events`). The time unit is the file's, else ``time_unit``, else
    microseconds.
    """
    recording = read_microseconds(path, sensor_size=sensor_size, time_unit=time_unit,
                                  **({} if columns is None else {"columns": columns}))
    return recording.events, recording.sensor_size


def method_name(transform: Downscaler) -> str:
    """The registry name of a transform's class (its class name when not registered)."""
    name = type(transform).name
    return name if METHODS.get(name) is type(transform) else type(transform).__name__


def panels(
    events: EventsLike,
    sensor_size: tuple[int, int, int],
    factor: int | tuple[int, int],
    methods: Sequence[str | Downscaler] | None = None,
    *,
    ground_truth: Panel | None = None,
    log: Callable[[str], None] | None = None,
) -> list[Panel]:
    """The input and its downscaled versions, one :class:`Panel` each.

    Args:
        events: a Tonic structured array, an ``(N, 4)`` tensor or Events (``t`` in
            microseconds).
        sensor_size: input ``(W, H, P)``.
        factor: the downscaling factor, ``f`` or ``(fx, fy)``.
        methods: registry names (built with their default settings by
            :func:`~evdown_torch.transforms.registry.make_method`) or transforms (whose own
            ``factor`` is used); default: every method of the registry.
        ground_truth: a last panel to add (e.g. :meth:`ShownRecording.ground_truth`).
        log: receives one line per method with its event count and time, if given.

    Returns:
        ``[input, method 1, ..., (ground truth)]``.

    Example:
        >>> import torch
        >>> ev = torch.tensor([[0, 0, 0, 1], [1, 1, 10, 1], [3, 3, 20, 0]])
        >>> [(p.name, p.events.num_events, p.sensor_size[:2])
        ...  for p in panels(ev, (4, 4, 2), 2, ["downsample", "event_count"])]
        [('input', 3, (4, 4)), ('downsample', 3, (2, 2)), ('event_count', 0, (2, 2))]
    """
    sensor_size = check_sensor_size(sensor_size)
    check_factor(factor, sensor_size)
    ev = sort_by_time(to_events(events, sensor_size)[0])
    chosen = list(METHODS) if methods is None else list(methods)
    out = [Panel("input", ev, sensor_size)]
    for method in chosen:
        transform = make_method(method, sensor_size, factor) if isinstance(method, str) else method
        if not isinstance(transform, Downscaler):
            raise TypeError(
                f"methods must be registry names or downscaling transforms, got {method!r}"
            )
        start = time.perf_counter()
        result = cast(Events, transform(ev))  # Events in, Events out
        name = method_name(transform)
        if log is not None:
            log(f"{name}: {result.num_events} events ({time.perf_counter() - start:.2f} s)")
        out.append(Panel(name, result, transform.output_sensor_size))
    if ground_truth is not None:
        out.append(ground_truth)
    return out


def to_numpy(events: Events) -> tuple:
    """``(x, y, t, on)`` as NumPy arrays (``t`` float64, exact below 2**53)."""
    return (events.x.cpu().numpy(), events.y.cpu().numpy(),
            events.t.to(torch.float64).cpu().numpy(), events.p.cpu().numpy())
