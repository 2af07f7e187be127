"""The recordings of a study: where they come from and where they are cached.

A :class:`StudyData` is a small picklable description of the dataset that every worker
process can read recordings through: synthetic gestures are generated once and cached as
``.npy`` files (and so are their low-resolution ground-truth renders); DVS128 Gesture and
N-MNIST are read from their own files through :class:`evdown_torch.data.sources.TonicSource`
and :class:`evdown_torch.data.sources.NMNISTSource`, the package's one way of opening each.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from evdown_torch.checks import check_factor
from evdown_torch.data.sources import NMNISTSource, TonicSource
from evdown_torch.evaluation.cache import Cache, code_fingerprint
from evdown_torch.evaluation.config import DataConfig

if TYPE_CHECKING:
    from evdown_torch.synthetic import SyntheticGestures

__all__ = ["StudyData", "check_available", "window"]

SPLITS = ("train", "test")


def window(events: np.ndarray) -> tuple[int, int]:
    """``(t_start, t_end)`` of a recording; ``(0, 0)`` when it is empty."""
    if len(events) == 0:
        return 0, 0
    return int(events["t"].min()), int(events["t"].max())


@dataclass(frozen=True)
class StudyData:
    """The recordings of ``config``, cached under ``cache_root``.

    Attributes:
        config: the ``[data]`` table.
        cache_root: the cache directory (a string, so that the source pickles small).
    """

    config: DataConfig
    cache_root: str

    @property
    def cache(self) -> Cache:
        """The cache the recordings are kept in."""
        return Cache(self.cache_root)

    @property
    def synthetic(self) -> bool:
        """Whether the recordings are synthetic gestures."""
        return self.config.dataset == "synthetic"

    @property
    def sensor_size(self) -> tuple[int, int, int]:
        """``(W, H, P)`` of the recordings."""
        return self.config.full_sensor_size

    @property
    def num_classes(self) -> int:
        """The number of classes (11 gestures, 10 digits)."""
        return self.config.num_classes

    @property
    def has_ground_truth(self) -> bool:
        """Whether low-resolution camera recordings exist (synthetic only)."""
        return self.synthetic

    def description(self) -> str:
        """A line naming the dataset, for the report."""
        c = self.config
        if self.synthetic:
            return (f"synthetic gestures (seed {c.seed}), {c.sensor_size[0]}x{c.sensor_size[1]}, "
                    f"{c.duration_us / 1e6:g} s")
        crop = f"first {c.duration_us / 1e6:g} s" if c.duration_us else "whole recordings"
        if c.dataset == "nmnist":
            return f"N-MNIST ({Path(c.root).expanduser()}), {crop}"
        return f"DVS128 Gesture ({Path(c.root).expanduser() / 'DVSGesture'}), {crop}"

    def size(self, split: str) -> int:
        """The number of recordings of ``split``."""
        wanted = self.config.train_samples if split == "train" else self.config.test_samples
        if self.synthetic:
            return wanted
        return len(_indices(self.config, split == "train"))

    def key(self, split: str) -> dict[str, Any]:
        """The settings that determine the recordings of ``split`` (index by index)."""
        c = self.config
        if self.synthetic:
            return {"dataset": "synthetic", "generator": code_fingerprint("synthetic"),
                    "sensor": list(c.sensor_size), "duration_us": c.duration_us,
                    "seed": c.seed, "split": split}
        return {"dataset": c.dataset, "root": str(Path(c.root).expanduser().resolve()),
                "duration_us": c.duration_us, "seed": c.seed, "split": split,
                "samples": c.train_samples if split == "train" else c.test_samples}

    def label(self, split: str, index: int) -> int:
        """The class of recording ``index`` of ``split``."""
        if self.synthetic:
            return index % self.num_classes
        return int(self.recording(split, index)[1])

    def _synthetic_dataset(self, split: str) -> SyntheticGestures:
        from evdown_torch.synthetic import SyntheticGestures

        c = self.config
        return SyntheticGestures(
            train=split == "train", samples_per_class=-(-self.size(split) // self.num_classes),
            duration_us=c.duration_us, seed=c.seed, sensor_size=self.sensor_size,
        )

    def _recording_path(self, split: str, index: int, factor: tuple[int, int]) -> Path:
        kind = "recordings" if factor == (1, 1) else "ground_truth"
        return self.cache.path(kind, {**self.key(split), "index": index,
                                      "factor": list(factor)}, ".npy")

    def ensure(self, split: str, index: int, factor: tuple[int, int] = (1, 1)) -> bool:
        """Generate and cache a synthetic recording (or its render at ``factor``) if absent.

        Returns:
            True when it had to be generated.
        """
        path = self._recording_path(split, index, factor)
        if path.is_file():
            return False
        dataset = self._synthetic_dataset(split)
        events = dataset[index][0] if factor == (1, 1) else dataset.ground_truth(index, factor)
        self.cache.save_array(path, events)
        return True

    def recording(self, split: str, index: int) -> tuple[np.ndarray, int]:
        """``(events, label)`` of recording ``index`` of ``split``."""
        if self.synthetic:
            self.ensure(split, index)
            return (Cache.load_array(self._recording_path(split, index, (1, 1))),
                    self.label(split, index))
        dataset = _opened(self.config.dataset, self.config.root, split == "train")
        events, label = dataset.load(_indices(self.config, split == "train")[index])
        if self.config.duration_us and len(events):
            events = events[events["t"] < events["t"].min() + self.config.duration_us]
        return events, int(label)

    def ground_truth(self, split: str, index: int, factor: tuple[int, int]) -> np.ndarray:
        """What a camera ``factor`` times smaller recorded of the same scene (synthetic only)."""
        if not self.synthetic:
            raise ValueError(f"the {self.config.dataset} dataset has no ground truth")
        factor = check_factor(factor, self.sensor_size)
        self.ensure(split, index, factor)
        return Cache.load_array(self._recording_path(split, index, factor))


@functools.cache
def _opened(dataset: str, root: str, train: bool) -> TonicSource | NMNISTSource:
    split = "train" if train else "test"
    if dataset == "nmnist":
        return NMNISTSource(root, split=split)
    return TonicSource(dataset, root=root, split=split)


@functools.cache
def _indices(config: DataConfig, train: bool) -> tuple[int, ...]:
    dataset = _opened(config.dataset, config.root, train)
    wanted = config.train_samples if train else config.test_samples
    order = torch.randperm(len(dataset), generator=torch.Generator().manual_seed(config.seed))
    return tuple(sorted(order[: wanted or len(dataset)].tolist()))


def check_available(config: DataConfig) -> None:
    """Raise a clear error when the configured dataset cannot be read.

    Raises:
        FileNotFoundError: for DVS128 Gesture absent from ``root`` (the message says where to
            put it).
        ValueError: for an N-MNIST folder that is absent or incomplete (the message names
            what is missing).
        RuntimeError: if tonic is missing.
    """
    if config.dataset == "synthetic":
        return
    try:
        import tonic
    except ModuleNotFoundError:
        raise RuntimeError(
            f"the {config.dataset} dataset needs tonic: pip install tonic (or "
            "evdown_torch[tonic])"
        ) from None
    if config.dataset == "nmnist":
        for split in SPLITS:
            NMNISTSource(config.root, split=split)
        return
    cls = tonic.datasets.DVSGesture
    location = Path(config.root).expanduser() / cls.__name__
    missing = [
        name
        for name in (cls.train_filename, cls.test_filename)
        if not (location / name).is_file()
        or not any((location / name.removesuffix(".tar.gz")).glob("**/*.npy"))
    ]
    if missing and not config.download:
        raise FileNotFoundError(
            f"DVS128 Gesture was not found in {str(location)!r} (missing or not extracted: "
            f"{', '.join(missing)}). tonic.datasets.DVSGesture(save_to={config.root!r}) expects "
            f"{cls.train_filename} and {cls.test_filename} in that folder, each extracted "
            f"there (folders ibmGestureTrain/ and ibmGestureTest/); get them from "
            f"{cls.train_url} and {cls.test_url}, or set download = true in [data] to let "
            "tonic fetch them"
        )
    if missing:
        for split in SPLITS:
            TonicSource("dvsgesture", root=config.root, split=split, download=True)
