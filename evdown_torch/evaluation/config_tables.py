"""The tables of an ``evdown evaluate`` config file, one frozen dataclass each.

:mod:`evdown_torch.evaluation.config` documents the file (every table and key, with its
default) and reads it into an :class:`~evdown_torch.evaluation.config.EvaluationConfig` of
these tables; each checks its own values where it is built, so a wrong one is an error that
names its table and key.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from evdown_torch.checks import (
    check_choice,
    check_factor,
    check_non_negative_int,
    check_positive_float,
    check_positive_int,
)
from evdown_torch.io import NMNIST_SENSOR
from evdown_torch.threads import check_threads
from evdown_torch.transforms.registry import METHODS

__all__ = [
    "DataConfig",
    "MeasuresConfig",
    "MethodsConfig",
    "ModelConfig",
    "OutputConfig",
    "RobustnessConfig",
    "StatisticsConfig",
    "TrainingConfig",
]

DATASETS = ("synthetic", "dvsgesture", "nmnist")
REFERENCES = ("camera", "input")
ENCODINGS = ("counts", "log", "binary")
CALIBRATIONS = ("training", "held_out")
DVS_GESTURE_SENSOR = (128, 128, 2)

#: Classes of each dataset (11 gestures: synthetic ones follow DVS128 Gesture's; 10 digits).
NUM_CLASSES = {"synthetic": 11, "dvsgesture": 11, "nmnist": 10}


@dataclass(frozen=True)
class DataConfig:
    """Which recordings, how many, and how they become frames (table ``[data]``)."""

    dataset: str = "synthetic"
    root: str = "data"
    download: bool = False
    sensor_size: tuple[int, int] = (128, 128)
    duration_us: int = 6_000_000
    train_samples: int = 264
    test_samples: int = 264
    calibration_samples: int = 22
    calibration: str = "training"
    train_per_seed: int = 0
    validation_samples: int = 0
    seed: int = 0
    time_bins: int = 6
    mean_time: bool = False
    folds: int = 0
    repeats: int = 1

    def __post_init__(self) -> None:
        check_choice("data.dataset", self.dataset, DATASETS)
        check_non_negative_int("data.folds", self.folds)
        check_positive_int("data.repeats", self.repeats)
        if self.folds == 1:
            raise ValueError("data.folds must be 0 (the dataset's own split) or at least 2, got 1")
        if self.folds and self.dataset != "nmnist":
            raise ValueError(
                f"data.folds cross-validates N-MNIST's pooled recordings; the {self.dataset} "
                "dataset keeps its own train and test split (set data.folds = 0)")
        if self.repeats > 1 and not self.folds:
            raise ValueError(f"data.repeats = {self.repeats} needs data.folds >= 2")
        for i, name in enumerate(("width", "height")):
            check_positive_int(f"data.sensor_size {name}", self.sensor_size[i])
        check_positive_int("data.time_bins", self.time_bins)
        check_non_negative_int("data.seed", self.seed)
        check_positive_int("data.calibration_samples", self.calibration_samples)
        check_choice("data.calibration", self.calibration, CALIBRATIONS)
        if self.calibration == "held_out" and self.dataset != "nmnist":
            raise ValueError(
                'data.calibration = "held_out" takes recordings of N-MNIST\'s Train that the '
                f"study does not use; the {self.dataset} dataset calibrates on its training "
                'recordings (data.calibration = "training")')
        if self.calibration == "held_out" and self.train_samples == 0:
            raise ValueError(
                'data.calibration = "held_out" needs recordings of Train left out of the study: '
                "set data.train_samples below the folder's Train recordings (0 takes them all)")
        check_non_negative_int("data.train_per_seed", self.train_per_seed)
        check_non_negative_int("data.validation_samples", self.validation_samples)
        if self.dataset == "synthetic" and self.validation_samples >= self.train_samples:
            raise ValueError(
                f"data.validation_samples ({self.validation_samples}) must leave training "
                f"recordings out of data.train_samples ({self.train_samples})"
            )
        if self.dataset == "synthetic":
            check_positive_int("data.duration_us", self.duration_us)
            check_positive_int("data.train_samples", self.train_samples)
            check_positive_int("data.test_samples", self.test_samples)
        else:
            for name in ("duration_us", "train_samples", "test_samples"):
                check_non_negative_int(f"data.{name}", getattr(self, name))

    @property
    def frame_channels(self) -> int:
        """Channels of the classifier's input, 2 (OFF and ON counts) or 4 (and their mean times)."""
        return 4 if self.mean_time else 2

    @property
    def full_sensor_size(self) -> tuple[int, int, int]:
        """``(W, H, 2)`` of the dataset's recordings."""
        if self.dataset == "dvsgesture":
            return DVS_GESTURE_SENSOR
        if self.dataset == "nmnist":
            return NMNIST_SENSOR
        return (self.sensor_size[0], self.sensor_size[1], 2)

    @property
    def num_classes(self) -> int:
        """The number of classes of the dataset."""
        return NUM_CLASSES[self.dataset]

    @property
    def fold_units(self) -> tuple[tuple[int, int], ...]:
        """Every ``(repeat, fold)`` of the cross-validation; ``((0, 0),)`` without folds."""
        if not self.folds:
            return ((0, 0),)
        return tuple((r, f) for r in range(self.repeats) for f in range(self.folds))


@dataclass(frozen=True)
class MethodsConfig:
    """Which methods and factors form the table's cells (table ``[methods]``)."""

    include: tuple[str, ...] | None = None
    factors: tuple[int | tuple[int, int], ...] = (2, 4)
    budget_reference: str = "camera"
    budgets: tuple[float, ...] = (1.0, 4.0)
    control: bool = True
    primary: tuple[str, ...] = ()
    primary_factors: tuple[int | tuple[int, int], ...] = ()
    primary_budget: float = 1.0
    primary_budgets: tuple[float, ...] = ()
    primary_peer: str = ""
    peers: tuple[str, ...] = ()
    sanity: bool = True
    live_delay: int = 0
    equivalence_margin: float = 0.03
    noninferiority: tuple[str, ...] = ()
    noninferiority_margin: float = 0.02
    full_resolution: bool = True
    native: bool = False
    tonic_peer: bool = False

    def __post_init__(self) -> None:
        check_choice("methods.budget_reference", self.budget_reference, REFERENCES)
        check_positive_float("methods.primary_budget", self.primary_budget)
        check_non_negative_int("methods.live_delay", self.live_delay)
        check_positive_float("methods.equivalence_margin", self.equivalence_margin)
        check_positive_float("methods.noninferiority_margin", self.noninferiority_margin)
        for factor in self.primary_factors:
            check_factor(factor)
        if self.noninferiority and (
                len(self.noninferiority) != 2 or not self.primary_factors
                or any(n not in METHODS or METHODS[n].budget_setting is None
                       for n in self.noninferiority)):
            raise ValueError(
                "methods.noninferiority must name [tested, reference], two methods with a "
                "budget setting, and needs methods.primary_factors; got "
                f"{list(self.noninferiority)}")
        if self.primary and not self.primary_factors:
            raise ValueError("methods.primary needs methods.primary_factors, got []")
        for budget in self.primary_budgets:
            check_positive_float("methods.primary_budgets", budget)
        if self.primary_budgets and len(self.primary_budgets) != len(self.primary_factors):
            raise ValueError(
                f"methods.primary_budgets must give one budget per primary factor "
                f"({len(self.primary_factors)}), got {list(self.primary_budgets)}")
        if self.primary_peer and (
                self.primary_peer not in METHODS or METHODS[self.primary_peer].budget_setting
                is None or self.primary_peer in self.primary or not self.primary):
            raise ValueError(
                f"methods.primary_peer must name a method with a budget setting that is not "
                f"itself primary, beside methods.primary; got {self.primary_peer!r}")
        for name in self.peers:
            if name not in METHODS or METHODS[name].budget_setting is None:
                raise ValueError(
                    f"methods.peers names {name!r}, which is not a method with a budget "
                    f"setting; those are "
                    f"{[n for n, m in METHODS.items() if m.budget_setting is not None]}")
        if self.peers and not self.primary_factors:
            raise ValueError("methods.peers needs methods.primary_factors, got []")
        for name in self.primary:
            if name not in METHODS or METHODS[name].budget_setting is None:
                raise ValueError(
                    f"methods.primary names {name!r}, which is not a method with a budget "
                    f"setting; those are "
                    f"{[n for n, m in METHODS.items() if m.budget_setting is not None]}"
                )
        for budget in self.budgets:
            check_positive_float("methods.budgets", budget)
        if len(set(self.budgets)) != len(self.budgets):
            raise ValueError(f"methods.budgets must be distinct, got {list(self.budgets)}")
        if not self.factors:
            raise ValueError("methods.factors must list at least one factor, got []")
        for factor in self.factors:
            check_factor(factor)
        if self.include is not None:
            unknown = [name for name in self.include if name not in METHODS]
            if unknown:
                raise ValueError(
                    f"methods.include names unknown method(s) {unknown}; the registry has "
                    f"{list(METHODS)}"
                )

    @property
    def all_factors(self) -> tuple[int | tuple[int, int], ...]:
        """The exploratory factors, then the primary ones not among them."""
        return tuple(dict.fromkeys((*self.factors, *self.primary_factors)))

    def budget_at(self, factor: int | tuple[int, int]) -> float:
        """The primary budget at ``factor``: ``primary_budgets``' entry, else ``primary_budget``.

        Example:
            >>> m = MethodsConfig(primary_factors=(2, 4), primary_budgets=(0.25, 0.05))
            >>> m.budget_at(4), m.budget_at((2, 2)), MethodsConfig().budget_at(8)
            (0.05, 0.25, 1.0)
        """
        wanted = check_factor(factor)
        for f, budget in zip(self.primary_factors, self.primary_budgets):
            if check_factor(f) == wanted:
                return budget
        return self.primary_budget

    @property
    def names(self) -> tuple[str, ...]:
        """The methods to evaluate, in the registry's order when ``include`` is not given."""
        if self.include is not None:
            return self.include
        return tuple(METHODS)


@dataclass(frozen=True)
class ModelConfig:
    """Settings of :class:`~evdown_torch.models.SpikingClassifier` (table ``[model]``)."""

    channels: tuple[int, ...] = (16, 32, 32, 32)
    pool_size: int = 1
    beta: float = 0.9
    threshold: float = 1.0
    grid: int = 16
    stem_channels: int = 8

    def __post_init__(self) -> None:
        check_non_negative_int("model.grid", self.grid)
        check_positive_int("model.stem_channels", self.stem_channels)
        if not self.channels:
            raise ValueError("model.channels must list at least one block, got []")
        for c in self.channels:
            check_positive_int("model.channels", c)
        check_positive_int("model.pool_size", self.pool_size)
        if not 0 < check_positive_float("model.beta", self.beta) <= 1:
            raise ValueError(f"model.beta must lie in (0, 1], got {self.beta!r}")
        check_positive_float("model.threshold", self.threshold)


@dataclass(frozen=True)
class TrainingConfig:
    """The training budget, identical for every cell (table ``[training]``)."""

    epochs: int = 10
    batch_size: int = 16
    learning_rate: float = 5e-3
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    primary_seeds: int = 10
    control_seeds: int = 0
    learning_rates: tuple[float, ...] = ()
    selection_seeds: int = 2
    normalise: bool = True
    full_resolution_seeds: int = 3
    encoding: str = "log"
    device: str = "auto"
    num_threads: int = 1
    workers: int = 2

    def __post_init__(self) -> None:
        check_positive_int("training.epochs", self.epochs)
        check_positive_int("training.batch_size", self.batch_size)
        check_positive_float("training.learning_rate", self.learning_rate)
        if not self.seeds:
            raise ValueError("training.seeds must list at least one seed, got []")
        for seed in self.seeds:
            check_non_negative_int("training.seeds", seed)
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"training.seeds must be distinct, got {list(self.seeds)}")
        check_choice("training.encoding", self.encoding, ENCODINGS)
        check_positive_int("training.primary_seeds", self.primary_seeds)
        check_non_negative_int("training.control_seeds", self.control_seeds)
        check_positive_int("training.selection_seeds", self.selection_seeds)
        for rate in self.learning_rates:
            check_positive_float("training.learning_rates", rate)
        if check_non_negative_int("training.num_threads", self.num_threads):
            check_threads(self.num_threads, "training.num_threads")
        check_non_negative_int("training.workers", self.workers)
        check_non_negative_int("training.full_resolution_seeds", self.full_resolution_seeds)
        if not self.device:
            raise ValueError("training.device must name a device, got ''")


    @property
    def baseline_seeds(self) -> tuple[int, ...]:
        """The seeds of the full-resolution cell."""
        return self.seeds[: self.full_resolution_seeds or len(self.seeds)]


@dataclass(frozen=True)
class StatisticsConfig:
    """Intervals and tests (table ``[statistics]``)."""

    confidence: float = 0.95
    resamples: int = 2000
    alpha: float = 0.05
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("confidence", "alpha"):
            value = check_positive_float(f"statistics.{name}", getattr(self, name))
            if value >= 1:
                raise ValueError(f"statistics.{name} must lie in (0, 1), got {value!r}")
        check_positive_int("statistics.resamples", self.resamples)
        check_non_negative_int("statistics.seed", self.seed)


@dataclass(frozen=True)
class MeasuresConfig:
    """Settings of the per-cell measures (table ``[measures]``)."""

    consistency_bin_us: int = 10_000
    consistency_recordings: int = 0
    throughput_recordings: int = 4

    def __post_init__(self) -> None:
        check_positive_int("measures.consistency_bin_us", self.consistency_bin_us)
        check_non_negative_int("measures.consistency_recordings", self.consistency_recordings)
        check_non_negative_int("measures.throughput_recordings", self.throughput_recordings)


@dataclass(frozen=True)
class OutputConfig:
    """Where the report and the cache go (table ``[output]``)."""

    directory: str = "results"
    cache: str = "results/cache"


@dataclass(frozen=True)
class RobustnessConfig:
    """The primary comparison again with a stronger classifier (table ``[robustness]``).

    Each of ``methods`` (primary methods) and the thinning control at ``factor`` (a primary
    factor) and its primary budget, on the same frames and seeds as the exploratory cells,
    trained with ``channels`` and ``epochs`` instead of ``model.channels`` and
    ``training.epochs``: does the gain hold for a classifier that learns more?
    """

    methods: tuple[str, ...] = ()
    factor: int | tuple[int, int] = 4
    channels: tuple[int, ...] = ()
    epochs: int = 0

    def __post_init__(self) -> None:
        check_factor(self.factor)
        for c in self.channels:
            check_positive_int("robustness.channels", c)
        check_non_negative_int("robustness.epochs", self.epochs)
        if self.methods and not self.channels and not self.epochs:
            raise ValueError("robustness.methods needs a stronger classifier: set "
                             "robustness.channels or robustness.epochs")

    @property
    def classifier(self) -> tuple[tuple[str, Any], ...]:
        """The rows' classifier settings, as a cell's ``classifier`` pairs."""
        return tuple((name, value) for name, value in (("channels", self.channels),
                                                       ("epochs", self.epochs)) if value)
