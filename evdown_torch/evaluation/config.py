"""Configuration of ``evdown evaluate``: TOML files mapped onto typed dataclasses.

A config file has up to nine tables; every key maps to a field below, so an unknown key, a
value of the wrong type or a missing file is an error that names the problem, never a silent
default. Keys left out take the defaults shown.

.. code-block:: toml

    [data]
    dataset = "synthetic"      # "synthetic" (evdown_torch.synthetic), "dvsgesture" (tonic) or
                               # "nmnist" (a folder in N-MNIST's layout)
    root = "data"              # dvsgesture: tonic's save_to (the dataset lies in ROOT/DVSGesture);
                               # nmnist: the folder holding Train/<digit>/*.bin and Test/...
    download = false           # dvsgesture: let tonic download it when absent
    sensor_size = [128, 128]   # synthetic: sensor width and height, pixels
    duration_us = 6_000_000    # synthetic: recording length; dvsgesture, nmnist: crop (0 = whole)
    train_samples = 264        # synthetic: number of samples; real data: at most (0 = all)
    test_samples = 264         # as train_samples, for the test split
    calibration_samples = 22   # the first training recordings, on which budgets are calibrated
    calibration = "training"   # "held_out" (nmnist): calibrate once, on recordings of Train
                               # that are not among train_samples (never in a test fold)
    train_per_seed = 0         # recordings each seed draws from the training pool (0: all)
    validation_samples = 0     # the first training recordings, held out to pick the rate
    seed = 0                   # which samples (synthetic scenes, subset of a real dataset)
    time_bins = 6              # frames per sample fed to the classifier
    mean_time = false          # add each bin's mean event time (OFF, ON) as two more channels
    folds = 0                  # nmnist: >= 2 pools Train and Test and cross-validates
                               # (stratified k-fold; 0: the dataset's own train/test split)
    repeats = 1                # with folds: repetitions, each with its own shuffle into folds

    [methods]
    include = ["downsample", "event_count"]   # default: every method of the registry
    factors = [2, 4]           # each an integer or a pair [fx, fy]
    budget_reference = "camera"  # "camera": the ground truth's count; "input": the input's
    budgets = [1.0, 4.0]       # each a multiple of the reference ([] : methods' own settings)
    control = true             # the thinning control (ThinnedDownsample) at each budget
    primary = ["event_count"]  # the primary family: each method against the control
    primary_factors = [4]      # ... at these factors
    primary_budget = 1.0       # ... at this budget (one-sided tests, Holm within the family)
    primary_budgets = []       # ... or one budget per primary factor, in order
    primary_peer = ""          # a budgeted method each primary method also faces ("density")
    peers = []                 # budgeted methods at each primary factor and budget, exploratory
    sanity = true              # Downsample at its own rate against its thinning, per factor
    live_delay = 0             # > 0: also LinearEstimation/CubicEstimation with this max_delay
    equivalence_margin = 0.03  # TOST margin of the "no difference" verdicts
    noninferiority = []        # [tested, reference]: at each primary factor and the primary
                               # budget, is tested at most noninferiority_margin worse?
    noninferiority_margin = 0.02
    full_resolution = true     # the full-resolution recordings as a row
    native = false             # each budgeted method also at its own settings (its native output)
    tonic_peer = false         # Tonic's EventDownsampling (integrator) at each factor

    [settings.event_count]     # one table per method: its settings (see `method_settings`);
    threshold = 1.0            # a budget setting given here is where calibration starts

    [model]                    # SpikingClassifier
    channels = [16, 32, 32, 32]
    pool_size = 1
    beta = 0.9
    threshold = 1.0
    grid = 16                  # stem stride = ceil(input side / grid); 0: no stem
    stem_channels = 8

    [training]
    epochs = 10
    batch_size = 16
    learning_rate = 0.005
    seeds = [0, 1, 2, 3, 4]    # one training run per seed (exploratory cells)
    primary_seeds = 10         # seeds 0..n-1 of each primary (and sanity) cell
    control_seeds = 0          # seeds of the primary control (0: ceil(sqrt(k) * primary_seeds))
    learning_rates = []        # candidates chosen per factor on the validation split ([]: none)
    selection_seeds = 2        # seeds per candidate rate
    normalise = true           # count channels divided by their RMS over the seed's training set
    full_resolution_seeds = 3  # the full-resolution cell trains on the first 3 (0: all)
    encoding = "log"           # classifier input: "counts", "log" (log1p of counts) or "binary"
    device = "auto"            # "cpu", "cuda", "cuda:1", ... or "auto"
    num_threads = 1            # torch threads of each process (0: leave torch's setting)
    workers = 2                # worker processes (0: everything in this process)

    [statistics]
    confidence = 0.95          # bootstrap intervals
    resamples = 2000           # per interval and test (at least 50,000 for a primary family)
    alpha = 0.05               # family-wise, Holm-corrected, per study
    seed = 0

    [measures]
    consistency_bin_us = 10_000  # optical consistency's time bins
    consistency_recordings = 0   # the first test recordings compared with the camera (0: all)
    throughput_recordings = 4    # test recordings timed per cell, one thread, idle

    [output]
    directory = "results"      # relative to the working directory
    cache = "results/cache"    # recordings, renders, frames and predictions, keyed by settings

    [robustness]               # the primary comparison again with a stronger classifier
    methods = []               # primary methods, each beside the control, exploratory
    factor = 4                 # a primary factor, at its primary budget
    channels = []              # the classifier's blocks for these rows ([]: model.channels)
    epochs = 0                 # their epochs (0: training.epochs)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evdown_torch.checks import (
    check_choice,
    check_factor,
    check_non_negative_int,
    check_positive_float,
    check_positive_int,
)
from evdown_torch.evaluation.toml_fields import section, toml_loads
from evdown_torch.io import NMNIST_SENSOR
from evdown_torch.threads import check_threads
from evdown_torch.transforms.registry import METHODS, make_method

__all__ = [
    "DataConfig",
    "EvaluationConfig",
    "MethodsConfig",
    "MeasuresConfig",
    "ModelConfig",
    "OutputConfig",
    "RobustnessConfig",
    "StatisticsConfig",
    "TrainingConfig",
    "load_config",
    "parse_config",
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


@dataclass(frozen=True)
class EvaluationConfig:
    """A whole ``evdown evaluate`` configuration.

    Attributes:
        data: the ``[data]`` table.
        methods: the ``[methods]`` table.
        model: the ``[model]`` table.
        training: the ``[training]`` table.
        statistics: the ``[statistics]`` table.
        measures: the ``[measures]`` table.
        output: the ``[output]`` table.
        robustness: the ``[robustness]`` table.
        settings: method name -> that method's settings (keyword arguments of
            :func:`~evdown_torch.transforms.registry.make_method`).
        name: a label for the report (the config file's stem).
    """

    data: DataConfig = field(default_factory=DataConfig)
    methods: MethodsConfig = field(default_factory=MethodsConfig)
    settings: dict[str, dict[str, Any]] = field(default_factory=dict)
    model: ModelConfig = field(default_factory=ModelConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    statistics: StatisticsConfig = field(default_factory=StatisticsConfig)
    measures: MeasuresConfig = field(default_factory=MeasuresConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    robustness: RobustnessConfig = field(default_factory=RobustnessConfig)
    name: str = "evaluation"

    def __post_init__(self) -> None:
        sensor = self.data.full_sensor_size
        if self.data.dataset != "synthetic" and self.methods.budget_reference == "camera" \
                and self.methods.budgets:
            raise ValueError(
                "methods.budget_reference = 'camera' needs the synthetic dataset's ground truth; "
                f"use 'input' for {self.data.dataset!r}"
            )
        for factor in self.methods.all_factors:
            try:
                check_factor(factor, sensor)
            except ValueError as error:
                raise ValueError(f"methods.factors: {error}") from None
        r = self.robustness
        if r.methods and (not set(r.methods) <= set(self.methods.primary) or check_factor(
                r.factor) not in [check_factor(f) for f in self.methods.primary_factors]):
            raise ValueError(
                f"robustness.methods must be primary methods and robustness.factor a primary "
                f"factor; got {list(r.methods)} at {r.factor!r}")
        for method, settings in self.settings.items():
            if method not in METHODS:
                raise ValueError(
                    f"[settings.{method}] names an unknown method; the registry has "
                    f"{list(METHODS)}"
                )
            for factor in self.methods.all_factors:
                try:
                    make_method(method, sensor, factor, **settings)
                except (ValueError, TypeError) as error:
                    raise type(error)(f"[settings.{method}]: {error}") from None

    def method_settings(self, method: str) -> dict[str, Any]:
        """The configured settings of ``method`` (empty: the method's defaults)."""
        return dict(self.settings.get(method, {}))


_SECTIONS = {
    "data": DataConfig,
    "methods": MethodsConfig,
    "model": ModelConfig,
    "training": TrainingConfig,
    "statistics": StatisticsConfig,
    "measures": MeasuresConfig,
    "output": OutputConfig,
    "robustness": RobustnessConfig,
}


def parse_config(document: dict[str, Any], *, name: str = "evaluation") -> EvaluationConfig:
    """Build an :class:`EvaluationConfig` from a parsed TOML document.

    Args:
        document: the tables, as ``tomllib.loads`` returns them.
        name: a label for the report.

    Returns:
        The validated configuration.

    Raises:
        ValueError: for an unknown table or key, or a value out of range.
        TypeError: for a value of the wrong type.

    Example:
        >>> config = parse_config({"methods": {"factors": [2, [2, 4]]}, "data": {"seed": 3}})
        >>> config.methods.factors, config.data.seed, config.training.epochs
        ((2, (2, 4)), 3, 10)
    """
    known = [*_SECTIONS, "settings"]
    for key in document:
        if key not in known:
            raise ValueError(f"unknown table [{key}]; a config takes tables {known}")
    sections = {
        key: section(cls, document[key], key) for key, cls in _SECTIONS.items() if key in document
    }
    settings = document.get("settings", {})
    if not isinstance(settings, dict) or not all(isinstance(v, dict) for v in settings.values()):
        raise TypeError(
            "[settings] must hold one table per method, e.g. [settings.event_count], "
            f"got {settings!r}"
        )
    return EvaluationConfig(**sections, settings=settings, name=name)


def load_config(path: str | Path, overrides: Sequence[str] = ()) -> EvaluationConfig:
    """Read and validate a TOML configuration file, with ``overrides`` applied.

    Args:
        path: the ``.toml`` file.
        overrides: ``"table.key=value"`` settings that replace (or add) a key of the file,
            the value written as in TOML (``"data.seed=1"``, ``'output.directory="x"'``).

    Returns:
        The :class:`EvaluationConfig`, named after the file's stem (and the overrides).

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError, TypeError: as :func:`parse_config`, with the file named in the message;
            for an override that is not ``table.key=value`` with a TOML value.

    Example:
        >>> import pathlib, tempfile
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "study.toml"
        >>> _ = path.write_text(chr(10).join(["[data]", "seed = 0"]))
        >>> config = load_config(path, ["data.seed=1"])
        >>> config.data.seed, config.name
        (1, 'study (data.seed=1)')
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {str(path)!r} does not exist")
    try:
        document = toml_loads(path.read_text(encoding="utf-8"))
        for override in overrides:
            _override(document, override)
        name = path.stem + (f" ({', '.join(overrides)})" if overrides else "")
        return parse_config(document, name=name)
    except (ValueError, TypeError) as error:
        raise type(error)(f"{path}: {error}") from None


def _override(document: dict[str, Any], override: str) -> None:
    """Apply one ``table.key=value`` override to a parsed ``document``, in place."""
    where, sep, text = override.partition("=")
    table, dot, key = where.strip().partition(".")
    if not sep or not dot or not table or not key or "." in key:
        raise ValueError(f"an override is table.key=value (e.g. data.seed=1), got {override!r}")
    try:
        value = toml_loads(f"value = {text.strip()}")["value"]
    except ValueError:
        raise ValueError(f"the value of {where.strip()} is not a TOML value (a string needs "
                         f"quotes), got {text.strip()!r}") from None
    section = document.setdefault(table, {})
    if not isinstance(section, dict):
        raise ValueError(f"{table} is not a table of the config, so {override!r} cannot set it")
    section[key] = value
