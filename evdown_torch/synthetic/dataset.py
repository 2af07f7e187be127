"""``SyntheticGestures``: a stand-in for ``tonic.datasets.DVSGesture``, generated on the fly."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, cast

import numpy as np
import torch

from evdown_torch.checks import (
    check_factor,
    check_item_index,
    check_non_negative_int,
    check_positive_int,
    check_sensor_size,
    output_size,
)
from evdown_torch.collate import apply_item_transforms
from evdown_torch.events import DVS_DTYPE as DVS_GESTURE_DTYPE
from evdown_torch.events import EventFormat, Events, from_events
from evdown_torch.synthetic.body_plan import GESTURE_CLASSES
from evdown_torch.synthetic.pixel_model import PixelModelConfig
from evdown_torch.synthetic.render import render_events
from evdown_torch.synthetic.scenes import GestureScene, scene_seed

__all__ = ["DVS_GESTURE_DTYPE", "SyntheticGestures", "render_gesture"]


_FORMAT = EventFormat("numpy", DVS_GESTURE_DTYPE, "bool", torch.device("cpu"))


def _structured(events: Events) -> np.ndarray:
    return cast(np.ndarray, from_events(events, _FORMAT))  # the numpy format gives an array


def render_gesture(
    label: int,
    seed: int,
    *,
    sensor_size: tuple[int, int, int] = (128, 128, 2),
    duration_us: int = 6_000_000,
    pixel_model: PixelModelConfig | None = None,
    factor: int | tuple[int, int] = 1,
) -> np.ndarray:
    """Render one gesture recording as a Tonic structured array (DVSGesture's dtype).

    ``render_gesture(label, seed, factor=f)`` is the same scene, motion, lighting, noise
    settings and readout as ``render_gesture(label, seed)``, seen by a sensor ``f`` times
    smaller whose pixels receive the mean photocurrent of the blocks they cover;
    ``factor=1`` is the recording.

    Args:
        label: class index into :data:`GESTURE_CLASSES`.
        seed: non-negative integer; the scene and all its randomness derive from it.
        sensor_size: ``(W, H, 2)`` of the full-resolution sensor.
        duration_us: length, microseconds.
        pixel_model: pixel parameters (default :class:`PixelModelConfig`).
        factor: ``f`` or ``(fx, fy)``; the output sensor is ``(ceil(W/fx), ceil(H/fy), 2)``.

    Returns:
        Structured array with fields ``x``, ``y`` (int16), ``p`` (bool), ``t`` (int64
        microseconds), sorted by ``t``.

    Example:
        >>> ev = render_gesture(1, seed=3, sensor_size=(32, 32, 2), duration_us=300_000)
        >>> ev.dtype.names, bool((ev["t"][1:] >= ev["t"][:-1]).all())
        (('x', 'y', 'p', 't'), True)
    """
    scene = GestureScene.sample(label, seed, sensor_size=sensor_size, duration_us=duration_us)
    return _structured(render_events(scene, pixel_model, factor=factor))


class SyntheticGestures:
    """Synthetic DVS128 Gesture recordings with the interface of ``tonic.datasets.DVSGesture``.

    Items are ``(events, label)``: a structured array in DVSGesture's dtype (``x``, ``y``
    int16, ``p`` bool, ``t`` int64 microseconds, sorted by ``t``) and the class index, after
    ``transform`` / ``target_transform`` / ``transforms`` as in Tonic. Samples are rendered
    on the fly from ``(seed, split, index)``, so nothing is stored and every access returns
    the same recording. Sample ``i`` has label ``i % 11``; the train and test splits draw
    their scenes from different derived seeds, so they share no recording.

    The constructor takes ``tonic.datasets.DVSGesture``'s arguments in its order
    (``save_to``, ``train``, ``transform``, ``target_transform``, ``transforms``), so
    ``SyntheticGestures("data", train=False)`` and ``DVSGesture("data", train=False)`` are
    swapped by one word; the generator's own settings are keyword-only.

    Args:
        save_to: accepted for DVSGesture's signature and unused: nothing is downloaded or
            stored (a path, or None).
        train: the training split (else the test split).
        transform: applied to the events.
        target_transform: applied to the label.
        transforms: applied to ``(events, label)`` together, last.
        samples_per_class: recordings per class in this split.
        duration_us: length of each recording, microseconds.
        seed: non-negative integer behind every scene of the dataset.
        sensor_size: ``(W, H, 2)``; the person scales with ``min(W, H)``.
        pixel_model: pixel parameters (default :class:`PixelModelConfig`).

    Attributes:
        classes: the 11 class names, in DVSGesture's order.
        sensor_size: ``(W, H, 2)``.
        dtype: DVSGesture's event dtype.
        ordering: its field names, ``("x", "y", "p", "t")``.
        targets: the label of every sample.

    Example:
        >>> data = SyntheticGestures(samples_per_class=2, duration_us=200_000,
        ...                          sensor_size=(32, 32, 2))
        >>> len(data), data.classes[3]
        (22, 'Right arm cw')
        >>> events, label = data[3]
        >>> label, events.dtype == data.dtype
        (3, True)
    """

    classes = list(GESTURE_CLASSES)
    sensor_size: tuple[int, int, int] = (128, 128, 2)
    dtype = DVS_GESTURE_DTYPE
    ordering = DVS_GESTURE_DTYPE.names

    def __init__(
        self,
        save_to: str | os.PathLike | None = None,
        train: bool = True,
        transform: Callable | None = None,
        target_transform: Callable | None = None,
        transforms: Callable | None = None,
        *,
        samples_per_class: int = 24,
        duration_us: int = 6_000_000,
        seed: int = 0,
        sensor_size: tuple[int, int, int] = (128, 128, 2),
        pixel_model: PixelModelConfig | None = None,
    ) -> None:
        if save_to is not None and not isinstance(save_to, (str, os.PathLike)):
            raise TypeError(
                f"save_to must be a path or None (unused: nothing is downloaded), got "
                f"{save_to!r}; train is the second argument, as in tonic's DVSGesture")
        if not isinstance(train, bool):
            raise TypeError(f"train must be a bool, got {train!r}")
        for name, fn in (("transform", transform), ("target_transform", target_transform),
                         ("transforms", transforms)):
            if fn is not None and not callable(fn):
                raise TypeError(f"{name} must be callable or None, got {fn!r}")
        self.save_to = save_to
        self.train = train
        self.transform = transform
        self.target_transform = target_transform
        self.transforms = transforms
        self.samples_per_class = check_positive_int("samples_per_class", samples_per_class)
        self.duration_us = check_positive_int("duration_us", duration_us)
        self.seed = check_non_negative_int("seed", seed)
        self.sensor_size = check_sensor_size(sensor_size)
        if self.sensor_size[2] != 2:
            raise ValueError(f"sensor_size must have 2 polarities, got {sensor_size!r}")
        if pixel_model is None:
            pixel_model = PixelModelConfig()
        if not isinstance(pixel_model, PixelModelConfig):
            raise TypeError(
                f"pixel_model must be a PixelModelConfig, got {type(pixel_model).__name__}"
            )
        self.pixel_model = pixel_model

    def __len__(self) -> int:
        return len(self.classes) * self.samples_per_class

    @property
    def targets(self) -> list[int]:
        """The label of every sample, in order."""
        return [i % len(self.classes) for i in range(len(self))]

    def _index(self, index: Any) -> int:
        return check_item_index(index, len(self), "samples")

    def scene(self, index: int) -> GestureScene:
        """The scene of sample ``index`` (its label is ``index % 11``)."""
        index = self._index(index)
        seed = scene_seed(self.seed, 0 if self.train else 1, index)
        return GestureScene.sample(index % len(self.classes), seed,
                                   sensor_size=self.sensor_size, duration_us=self.duration_us)

    def __getitem__(self, index: int) -> tuple[Any, Any]:
        """``(events, label)`` of sample ``index``, after the transforms."""
        scene = self.scene(index)
        events: Any = _structured(render_events(scene, self.pixel_model))
        target: Any = scene.label
        return apply_item_transforms(self, events, target)

    def ground_truth(self, index: int, factor: int | tuple[int, int]) -> np.ndarray:
        """Sample ``index`` as a sensor ``factor`` times smaller would have recorded it.

        The same scene, motion, lighting, pixel parameters, noise settings and readout,
        rendered on a sensor
        ``(ceil(W / fx), ceil(H / fy), 2)`` whose pixels receive the mean linear intensity
        (photocurrent) of the block of full-resolution pixels they cover (edge blocks: the
        pixels inside the sensor). At ``factor=1`` this is exactly the sample's events.
        No transform is applied.

        Args:
            index: sample index.
            factor: ``f`` or ``(fx, fy)``, positive integers no larger than the sensor.

        Returns:
            Structured array in DVSGesture's dtype, sorted by ``t``.

        Example:
            >>> data = SyntheticGestures(samples_per_class=1, duration_us=100_000,
            ...                          sensor_size=(32, 32, 2))
            >>> low = data.ground_truth(0, 4)
            >>> bool(low["x"].max(initial=0) < 8 and low["y"].max(initial=0) < 8)
            True
        """
        check_factor(factor, self.sensor_size)
        return _structured(render_events(self.scene(index), self.pixel_model, factor=factor))

    def ground_truth_sensor_size(self, factor: int | tuple[int, int]) -> tuple[int, int, int]:
        """Sensor size ``(ceil(W / fx), ceil(H / fy), 2)`` of :meth:`ground_truth`."""
        return output_size(self.sensor_size, check_factor(factor, self.sensor_size))

    def __repr__(self) -> str:
        split = "train" if self.train else "test"
        return (f"SyntheticGestures({split}, {len(self)} samples, sensor_size="
                f"{self.sensor_size}, duration_us={self.duration_us}, seed={self.seed})")
