"""The recordings of a study: where they come from and where they are cached.

A :class:`StudyData` is a small picklable description of the dataset that every worker
process can read recordings through: synthetic gestures are generated once and cached as
``.npy`` files (and so are their low-resolution ground-truth renders); DVS128 Gesture and
N-MNIST are read from their own files through :class:`evdown_torch.data.sources.TonicSource`
and :class:`evdown_torch.data.sources.NMNISTSource`, the package's one way of opening each.

With ``data.folds`` (real data) the dataset's train and test recordings are pooled and dealt
into stratified folds, once per repeat; ``StudyData(..., fold=(r, f))`` then reads fold ``f``
of repeat ``r`` as its test split and the other folds as its training split
(:func:`fold_assignment`); the split ``"pooled"`` reads every pooled recording, the same for
every fold, so that a cell's frames are made once for all folds (:meth:`StudyData.positions`
maps a fold's splits onto it). With ``data.calibration = "held_out"`` (N-MNIST) a split
``"calibration"``, holds ``data.calibration_samples`` recordings of the folder's Train that
the study does not otherwise use: the same for every fold, and never in a test fold.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch

from evdown_torch.checks import check_factor
from evdown_torch.data.sources import NMNISTSource, TonicSource
from evdown_torch.evaluation.cache import Cache, code_fingerprint
from evdown_torch.evaluation.config import DataConfig

if TYPE_CHECKING:
    from evdown_torch.synthetic import SyntheticGestures

__all__ = ["CALIBRATION", "POOLED", "StudyData", "check_available", "fold_assignment",
           "outside_study", "window"]

SPLITS = ("train", "test")
#: The split budgets are calibrated on: the held-out one, or the first training recordings.
CALIBRATION = "calibration"
#: Every recording pooled by ``data.folds``, in pooled order (the same for every fold).
POOLED = "pooled"


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
        fold: ``(repeat, fold)`` of the cross-validation (``data.folds``), ``None`` for the
            dataset's own split.
    """

    config: DataConfig
    cache_root: str
    fold: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if (self.fold is None) != (not self.config.folds):
            raise ValueError(
                f"StudyData needs a fold exactly when data.folds is set (data.folds = "
                f"{self.config.folds}, fold = {self.fold})")
        if self.fold is not None and self.fold not in self.config.fold_units:
            raise ValueError(f"fold {self.fold} is not a (repeat, fold) of data.repeats = "
                             f"{self.config.repeats} and data.folds = {self.config.folds}")

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
        if c.folds:
            crop += (f"; Train and Test pooled, {c.repeats} x {c.folds}-fold stratified "
                     "cross-validation")
        if c.dataset == "nmnist":
            return f"N-MNIST ({Path(c.root).expanduser()}), {crop}"
        return f"DVS128 Gesture ({Path(c.root).expanduser() / 'DVSGesture'}), {crop}"

    @property
    def calibration_split(self) -> str:
        """The split budgets are calibrated on: ``"calibration"`` (held out) or ``"train"``."""
        return CALIBRATION if self.config.calibration == "held_out" else "train"

    def size(self, split: str) -> int:
        """The number of recordings of ``split``."""
        if split == CALIBRATION:
            return len(_held_out(self.config))
        if split == POOLED:
            return self.pooled_size
        wanted = self.config.train_samples if split == "train" else self.config.test_samples
        if self.synthetic:
            return wanted
        if self.fold is not None:
            return len(self._fold_split(split))
        return len(_indices(self.config, split == "train"))

    @property
    def pooled_size(self) -> int:
        """The recordings of both splits together (what ``data.folds`` deals into folds)."""
        return len(_pooled(self.config))

    @property
    def test_positions(self) -> tuple[int, ...]:
        """Positions in the pooled recordings of this fold's test recordings, in order."""
        return self.positions("test")

    def positions(self, split: str) -> tuple[int, ...]:
        """Positions in the pooled recordings of this fold's ``split``, in its order.

        Recording ``i`` of ``split`` is recording ``positions(split)[i]`` of ``"pooled"``.

        Raises:
            ValueError: without a fold.
        """
        if self.fold is None:
            raise ValueError("positions need a fold (data.folds >= 2)")
        return self._fold_split(split)

    def _fold_split(self, split: str) -> tuple[int, ...]:
        train, test = _fold_splits(self.config, *cast(tuple[int, int], self.fold))
        return train if split == "train" else test

    def key(self, split: str) -> dict[str, Any]:
        """The settings that determine the recordings of ``split`` (index by index)."""
        c = self.config
        if self.synthetic:
            return {"dataset": "synthetic", "generator": code_fingerprint("synthetic"),
                    "sensor": list(c.sensor_size), "duration_us": c.duration_us,
                    "seed": c.seed, "split": split}
        key = {"dataset": c.dataset, "root": str(Path(c.root).expanduser().resolve()),
               "duration_us": c.duration_us, "seed": c.seed, "split": split,
               "samples": c.train_samples if split == "train" else c.test_samples}
        if split == CALIBRATION:  # the same in every fold
            key["samples"] = [c.train_samples, c.calibration_samples]
        elif split == POOLED:  # the same in every fold
            key["samples"] = [c.train_samples, c.test_samples]
        elif self.fold is not None:
            key["cross_validation"] = [c.train_samples, c.test_samples, c.folds, *self.fold]
            key["samples"] = None
        return key

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
        train = split in ("train", CALIBRATION)
        if split == CALIBRATION:
            index = _held_out(self.config)[index]
        elif split == POOLED:
            train, index = _pooled(self.config)[index]
        elif self.fold is not None:
            train, index = _pooled(self.config)[self._fold_split(split)[index]]
        else:
            index = _indices(self.config, train)[index]
        events, label = _opened(self.config.dataset, self.config.root, train).load(index)
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


def outside_study(config: DataConfig) -> list[int]:
    """Indices, in order, of the folder's Train recordings the study does not draw."""
    used = set(_indices(config, True))
    return [i for i in range(len(_opened(config.dataset, config.root, True))) if i not in used]


@functools.cache
def _held_out(config: DataConfig) -> tuple[int, ...]:
    """Indices in the folder's Train of the held-out calibration recordings.

    ``data.calibration_samples`` of the Train recordings that :func:`_indices` did not take,
    in an order seeded by ``data.seed`` (so a mix of classes).

    Raises:
        ValueError: if fewer remain.
    """
    rest = outside_study(config)
    if len(rest) < config.calibration_samples:
        used = len(_indices(config, True))
        raise ValueError(
            f"data.calibration = \"held_out\" needs {config.calibration_samples} recordings of "
            f"Train outside the study's {used}, but {config.root!r} has {used + len(rest)} "
            "in Train: lower data.train_samples or data.calibration_samples")
    order = torch.randperm(len(rest), generator=torch.Generator().manual_seed(config.seed + 1))
    return tuple(rest[i] for i in order[: config.calibration_samples].tolist())


@functools.cache
def _pooled(config: DataConfig) -> tuple[tuple[bool, int], ...]:
    """``(from the train split, index there)`` of every recording of both splits."""
    return tuple((train, i) for train in (True, False) for i in _indices(config, train))


def fold_assignment(labels: list[int], folds: int, seed: int) -> tuple[list[int], list[int]]:
    """Deal recordings into ``folds`` stratified folds.

    A seeded permutation orders the recordings; each class's recordings, in that order, are
    dealt round-robin onto the folds, each class starting where the previous one stopped, so
    that every fold holds each class within one recording of its share and the folds' sizes
    differ by at most one.

    Args:
        labels: the class of each recording.
        folds: the number of folds (>= 2).
        seed: seeds the permutation (one per repeat).

    Returns:
        ``(order, fold_of)``: the permutation (recording indices) and the fold of each
        recording.

    Example:
        >>> order, fold_of = fold_assignment([0, 0, 0, 1, 1, 1], 3, seed=0)
        >>> sorted(order), sorted(fold_of)
        ([0, 1, 2, 3, 4, 5], [0, 0, 1, 1, 2, 2])
        >>> [sorted(fold_of[i] for i in range(6) if i // 3 == y) for y in (0, 1)]
        [[0, 1, 2], [0, 1, 2]]
    """
    order = torch.randperm(len(labels), generator=torch.Generator().manual_seed(seed)).tolist()
    fold_of = [0] * len(labels)
    start = 0
    for label in sorted(set(labels)):
        members = [i for i in order if labels[i] == label]
        for j, i in enumerate(members):
            fold_of[i] = (start + j) % folds
        start += len(members)
    return order, fold_of


@functools.cache
def _fold_splits(config: DataConfig, repeat: int, fold: int
                 ) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Pooled positions of fold ``fold`` of ``repeat``'s training and test splits.

    The training split keeps the repeat's shuffled order (so that its first recordings, the
    calibration and validation ones, are a random mix of classes); the test split is sorted.
    """
    labels = [cast(NMNISTSource, _opened(config.dataset, config.root, train)).labels[i]
              for train, i in _pooled(config)]
    order, fold_of = fold_assignment(labels, config.folds, config.seed * 1009 + repeat)
    train = tuple(i for i in order if fold_of[i] != fold)
    test = tuple(i for i in range(len(labels)) if fold_of[i] == fold)
    return train, test


def check_available(config: DataConfig) -> None:
    """Raise a clear error when the configured dataset cannot be read.

    Raises:
        FileNotFoundError: for DVS128 Gesture absent from ``root`` (the message says where to
            put it).
        ValueError: for an N-MNIST folder that is absent or incomplete (the message names
            what is missing), or too small for ``data.calibration = "held_out"``.
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
        if config.calibration == "held_out":
            _held_out(config)
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
