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

from evdown_torch.checks import check_factor
from evdown_torch.evaluation.config_tables import (
    DataConfig,
    MeasuresConfig,
    MethodsConfig,
    ModelConfig,
    OutputConfig,
    RobustnessConfig,
    StatisticsConfig,
    TrainingConfig,
)
from evdown_torch.evaluation.toml_fields import section, toml_loads
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
