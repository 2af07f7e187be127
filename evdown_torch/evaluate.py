"""The speed/accuracy trade of the downscalers, measured: ``evdown evaluate --config FILE``.

For every method of :data:`~evdown_torch.transforms.registry.METHODS` (or the configured
subset) and every configured factor, plus the full-resolution baseline, the evaluation

1. downscales every recording of the dataset (once per cell; the frames stay in memory),
2. trains the same :class:`~evdown_torch.models.SpikingClassifier` with the same budget, once
   per configured seed (the seed fixes the initial weights and the order of the batches), and
3. reports per cell (method, factor):

   * **accuracy**: test accuracy, mean and standard deviation over the seeds;
   * **events/sample**: mean number of output events per recording (train and test);
   * **reduction**: total input events / total output events (1 for the baseline);
   * **throughput**: input events downscaled per second of the transform's own time
     (measured on this run, with the configured number of torch threads);
   * **density** and **entropy**: the paper's temporal density (events per pixel per
     microsecond) and information entropy (bits per pixel and polarity) of
     :mod:`evdown_torch.metrics`, per recording over the source recording's duration, averaged;
   * **consistency** (optical consistency), for synthetic data: how well the downscaled stream
     agrees with what a real camera of the lower resolution would have recorded, the
     generator's ground truth rendered on the small sensor. Both streams are binned into
     per-polarity event-count frames (``time_bins`` bins over the source recording's time
     window, :func:`~evdown_torch.frames.to_frames`), and the measure is the cosine similarity
     of the two flattened count tensors, averaged over the test recordings. It lies in
     ``[0, 1]``; it ignores the overall event rate (a stream with every count doubled scores
     the same) and rewards events at the right place, polarity and time. The CSV also gives
     the rate ratio, output events / ground-truth events (test recordings, inside the
     window). The baseline's consistency is 1 by definition (the ground truth at factor 1 is
     the recording itself); real datasets have no ground truth ("n/a").

Results go to ``results.csv``, ``report.md`` (a Markdown table ready to paste) and
``tradeoff.png`` (accuracy against throughput and against event reduction; needs matplotlib)
in the output directory. Runs are deterministic for a given config on one device and number of
threads, except for the measured times.
"""

from __future__ import annotations

import csv
import math
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import DataLoader, TensorDataset

from evdown_torch.config import DataConfig, EvaluationConfig
from evdown_torch.events import Events, EventsLike, to_events
from evdown_torch.frames import to_frames
from evdown_torch.metrics import event_metrics
from evdown_torch.models.classifier import SpikingClassifier
from evdown_torch.training import evaluate_classifier, train_classifier
from evdown_torch.transforms.registry import make_method

__all__ = [
    "BASELINE",
    "CellResult",
    "EvaluationData",
    "EvaluationResult",
    "load_data",
    "run_evaluation",
    "write_report",
]

#: The method name of the full-resolution row.
BASELINE = "full resolution"

Log = Callable[[str], None]


@dataclass(frozen=True)
class EvaluationData:
    """The recordings an evaluation runs on.

    Attributes:
        description: one line for the report, e.g. ``"synthetic gestures, 64x64, 1.5 s"``.
        sensor_size: ``(W, H, 2)`` of the recordings.
        num_classes: number of classes; labels are ``0 .. num_classes - 1``.
        train: ``(events, label)`` items (any event kind :func:`~evdown_torch.to_events`
            takes), read once per cell; a list or a lazily loading dataset.
        test: the same, for the test split.
        ground_truth: ``ground_truth(i, (fx, fy))`` returns the events a camera with a sensor
            ``(ceil(W / fx), ceil(H / fy))`` would have recorded of test recording ``i``, or
            ``None`` when the dataset has no such ground truth.
    """

    description: str
    sensor_size: tuple[int, int, int]
    num_classes: int
    train: Sequence[tuple[EventsLike, int]]
    test: Sequence[tuple[EventsLike, int]]
    ground_truth: Callable[[int, tuple[int, int]], EventsLike] | None = None


@dataclass(frozen=True)
class CellResult:
    """The measurements of one (method, factor) cell.

    Attributes:
        method: the method's registry name, or :data:`BASELINE`.
        factor: ``(fx, fy)``; ``(1, 1)`` for the baseline.
        output_size: ``(W, H)`` of the downscaled sensor.
        accuracies: test accuracy of each seed, in ``[0, 1]``.
        events_per_sample: mean output events per recording.
        reduction: total input events / total output events (``inf`` with no output).
        throughput: input events per second of downscaling; ``None`` for the baseline.
        density: mean temporal density, events per pixel per time unit (microsecond).
        entropy: mean information entropy, bits.
        consistency: mean cosine similarity with the ground truth; ``None`` without one.
        rate_vs_ground_truth: output events / ground-truth events; ``None`` without one.
        downscale_seconds: time spent in the transform, all recordings.
        train_seconds: mean training time per seed.
    """

    method: str
    factor: tuple[int, int]
    output_size: tuple[int, int]
    accuracies: tuple[float, ...]
    events_per_sample: float
    reduction: float
    throughput: float | None
    density: float
    entropy: float
    consistency: float | None
    rate_vs_ground_truth: float | None
    downscale_seconds: float
    train_seconds: float

    @property
    def accuracy_mean(self) -> float:
        """Mean accuracy over the seeds."""
        return statistics.fmean(self.accuracies)

    @property
    def accuracy_std(self) -> float:
        """Sample standard deviation of the accuracy over the seeds (0 for one seed)."""
        return statistics.stdev(self.accuracies) if len(self.accuracies) > 1 else 0.0


@dataclass(frozen=True)
class EvaluationResult:
    """All cells of one run, the baseline first, how long the run took, on how many threads."""

    config: EvaluationConfig
    description: str
    cells: tuple[CellResult, ...]
    wall_seconds: float
    threads: int


class _Progress:
    """One line per step on stderr, with the seconds elapsed since the start."""

    def __init__(self, log: Log | None) -> None:
        self.start = time.perf_counter()
        self.log = log

    def __call__(self, message: str) -> None:
        if self.log is not None:
            self.log(f"[{time.perf_counter() - self.start:7.1f} s] {message}")


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- data


def load_data(config: DataConfig, log: Log | None = None) -> EvaluationData:
    """Load the configured dataset.

    Args:
        config: the ``[data]`` table.
        log: receives progress lines, if given.

    Returns:
        The recordings.

    Raises:
        FileNotFoundError: for DVS128 Gesture absent from ``root`` (the message says where
            to put it).
        RuntimeError: if a needed optional package (tonic) is missing.
    """
    if config.dataset == "dvsgesture":
        return _load_dvsgesture(config, log)
    return _load_synthetic(config, log)


def _load_synthetic(config: DataConfig, log: Log | None) -> EvaluationData:
    from evdown_torch.synthetic import SyntheticGestures

    sensor = config.full_sensor_size
    splits = []
    for train, wanted in ((True, config.train_samples), (False, config.test_samples)):
        dataset = SyntheticGestures(
            train=train,
            samples_per_class=-(-wanted // len(SyntheticGestures.classes)),
            duration_us=config.duration_us,
            seed=config.seed,
            sensor_size=sensor,
        )
        splits.append((dataset, [dataset[i] for i in range(wanted)]))
        if log is not None:
            events = sum(len(events) for events, _ in splits[-1][1])
            log(f"rendered {wanted} synthetic {'train' if train else 'test'} recordings "
                f"({events / wanted:,.0f} events each)")
    test = splits[1][0]
    return EvaluationData(
        description=f"synthetic gestures (seed {config.seed}), {sensor[0]}x{sensor[1]}, "
        f"{config.duration_us / 1e6:g} s",
        sensor_size=sensor,
        num_classes=len(SyntheticGestures.classes),
        train=splits[0][1],
        test=splits[1][1],
        ground_truth=lambda index, factor: test.ground_truth(index, factor),
    )


class _Cropped:
    """A tonic dataset's items, the first ``duration_us`` of each recording (lazy)."""

    def __init__(self, dataset, indices: list[int], duration_us: int) -> None:
        self.dataset, self.indices, self.duration_us = dataset, indices, duration_us

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> tuple[EventsLike, int]:
        events, label = self.dataset[self.indices[i]]
        if self.duration_us and len(events):
            events = events[events["t"] < events["t"].min() + self.duration_us]
        return events, int(label)


def _load_dvsgesture(config: DataConfig, log: Log | None) -> EvaluationData:
    try:
        import tonic
    except ModuleNotFoundError:
        raise RuntimeError(
            "the dvsgesture dataset needs tonic: pip install tonic (or evdown_torch[tonic])"
        ) from None
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
    splits = []
    for train, wanted in ((True, config.train_samples), (False, config.test_samples)):
        dataset = cls(save_to=config.root, train=train)
        order = torch.randperm(len(dataset), generator=torch.Generator().manual_seed(config.seed))
        indices = sorted(order[: wanted or len(dataset)].tolist())
        splits.append(_Cropped(dataset, indices, config.duration_us))
    crop = f"first {config.duration_us / 1e6:g} s" if config.duration_us else "whole recordings"
    return EvaluationData(
        description=f"DVS128 Gesture ({location}), {crop}",
        sensor_size=cls.sensor_size,
        num_classes=len(cls.classes),
        train=splits[0],
        test=splits[1],
    )


# ----------------------------------------------------------------------------- one cell


def _encode(counts: Tensor, encoding: str) -> Tensor:
    """Classifier input from event counts.

    ``"log"`` (``log1p``, to three significant digits) and ``"binary"`` (exact) are stored as
    float16 to halve the memory of the cached frames, ``"counts"`` as float32 (exact).
    """
    if encoding == "log":
        return torch.log1p(counts).to(torch.float16)
    if encoding == "binary":
        return (counts > 0).to(torch.float16)
    return counts.to(torch.float32)


def _cosine(a: Tensor, b: Tensor) -> float:
    """Cosine similarity of two count tensors; 1 when both are empty, 0 when one is."""
    a, b = a.flatten().double(), b.flatten().double()
    na, nb = float(a.norm()), float(b.norm())
    if na == 0 or nb == 0:
        return 1.0 if na == nb else 0.0
    return float(a @ b) / (na * nb)


@dataclass
class _Prepared:
    """A cell's frames and stream statistics, before training."""

    train_x: Tensor
    train_y: Tensor
    test_x: Tensor
    test_y: Tensor
    events_in: int
    events_out: int
    samples: int
    seconds: float
    density: float
    entropy: float
    consistency: float | None
    rate_vs_ground_truth: float | None


def _prepare(
    data: EvaluationData,
    transform: Callable[[Events], Events] | None,
    out_sensor: tuple[int, int, int],
    config: EvaluationConfig,
    ground_truth: list[Tensor] | None,
) -> _Prepared:
    """Downscale (or not, for ``transform=None``) every recording and bin it into frames.

    ``ground_truth`` holds the ground truth's count frames of each test recording.
    """
    bins = config.data.time_bins
    seconds = 0.0
    events_in = events_out = 0
    test_out = 0.0
    densities, entropies, cosines = [], [], []
    splits = []
    for split_name, split in (("train", data.train), ("test", data.test)):
        frames, labels = [], []
        for i in range(len(split)):
            raw, label = split[i]
            source, _ = to_events(raw, data.sensor_size)
            if transform is None:
                out = source
            else:
                start = time.perf_counter()
                out = transform(source)
                seconds += time.perf_counter() - start
            window = _window(source)
            counts = to_frames(out, out_sensor, bins, t_start=window[0], t_end=window[1])
            if split_name == "test" and ground_truth is not None:
                cosines.append(_cosine(counts, ground_truth[i]))
                test_out += float(counts.sum())
            metrics = event_metrics(out, out_sensor, duration=window[2])
            densities.append(metrics.density)
            entropies.append(metrics.entropy)
            events_in += source.num_events
            events_out += out.num_events
            frames.append(_encode(counts, config.training.encoding))
            labels.append(int(label))
        if not frames:
            raise ValueError(f"the {split_name} split has no recordings")
        splits.append((torch.stack(frames), torch.tensor(labels, dtype=torch.int64)))
    consistency = rate = None
    if ground_truth is not None:
        consistency = statistics.fmean(cosines)
        gt_events = sum(float(x.sum()) for x in ground_truth)
        rate = test_out / gt_events if gt_events else math.inf
    return _Prepared(
        splits[0][0], splits[0][1], splits[1][0], splits[1][1],
        events_in, events_out, len(data.train) + len(data.test), seconds,
        statistics.fmean(densities), statistics.fmean(entropies), consistency, rate,
    )


def _window(source: Events) -> tuple[int | float | None, int | float | None, float]:
    """``(t_start, t_end, duration)`` of a source recording (duration at least 1 time unit)."""
    if source.num_events == 0:
        return None, None, 1.0
    t0, t1 = source.t.min().item(), source.t.max().item()
    return t0, t1, max(float(t1 - t0), 1.0)


def _ground_truth_frames(
    data: EvaluationData, factor: tuple[int, int], out_sensor: tuple[int, int, int], bins: int
) -> list[Tensor] | None:
    """Count frames of the ground truth of every test recording, binned like the outputs."""
    if data.ground_truth is None:
        return None
    frames = []
    for i in range(len(data.test)):
        source, _ = to_events(data.test[i][0], data.sensor_size)
        t0, t1, _ = _window(source)
        frames.append(to_frames(data.ground_truth(i, factor), out_sensor, bins, t_start=t0,
                                t_end=t1))
    return frames


def _resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"training.device {name!r} is not a torch device") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"training.device is {name!r} but CUDA is not available here")
    return device


def _train_once(
    prepared: _Prepared, config: EvaluationConfig, num_classes: int, seed: int,
    device: torch.device,
) -> float:
    """Train a fresh classifier under ``seed`` and return its test accuracy."""
    model_config, training = config.model, config.training
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = SpikingClassifier(
            num_classes,
            channels=model_config.channels,
            pool_size=model_config.pool_size,
            beta=model_config.beta,
            threshold=model_config.threshold,
        )
    model.to(device)
    order = torch.Generator().manual_seed(seed)
    train_loader = DataLoader(
        TensorDataset(prepared.train_x, prepared.train_y),
        batch_size=training.batch_size, shuffle=True, generator=order,
    )
    test_loader = DataLoader(
        TensorDataset(prepared.test_x, prepared.test_y), batch_size=training.batch_size
    )
    train_classifier(model, train_loader, epochs=training.epochs,
                     learning_rate=training.learning_rate)
    return evaluate_classifier(model, test_loader)


def _cell(
    name: str, factor: tuple[int, int], data: EvaluationData, config: EvaluationConfig,
    device: torch.device, ground_truth: list[Tensor] | None, progress: _Progress,
) -> CellResult:
    label = BASELINE if name == BASELINE else f"{name} x{_factor_text(factor)}"
    if name == BASELINE:
        transform, out_sensor = None, data.sensor_size
    else:
        down = make_method(name, data.sensor_size, factor, **config.method_settings(name))
        transform, out_sensor = down, down.output_sensor_size
    prepared = _prepare(data, transform, out_sensor, config, ground_truth)
    throughput = None
    if transform is not None:
        throughput = prepared.events_in / prepared.seconds if prepared.seconds > 0 else math.inf
    rate_text = "" if throughput is None else f" at {throughput / 1e6:.2f} M events/s"
    progress(
        f"{label}: {prepared.samples} recordings{rate_text}, "
        f"{prepared.events_out / prepared.samples:,.0f} events/recording"
    )
    accuracies, train_seconds = [], []
    for seed in config.training.seeds:
        start = time.perf_counter()
        accuracies.append(_train_once(prepared, config, data.num_classes, seed, device))
        train_seconds.append(time.perf_counter() - start)
        progress(f"{label}, seed {seed}: accuracy {accuracies[-1]:.3f} "
                 f"(trained in {train_seconds[-1]:.1f} s)")
    consistency, rate = prepared.consistency, prepared.rate_vs_ground_truth
    if name == BASELINE and data.ground_truth is not None:
        consistency = rate = 1.0  # the ground truth at factor 1 is the recording itself
    return CellResult(
        method=name,
        factor=factor,
        output_size=(out_sensor[0], out_sensor[1]),
        accuracies=tuple(accuracies),
        events_per_sample=prepared.events_out / prepared.samples,
        reduction=(prepared.events_in / prepared.events_out if prepared.events_out else math.inf),
        throughput=throughput,
        density=prepared.density,
        entropy=prepared.entropy,
        consistency=consistency,
        rate_vs_ground_truth=rate,
        downscale_seconds=prepared.seconds,
        train_seconds=statistics.fmean(train_seconds),
    )


def run_evaluation(
    config: EvaluationConfig, *, data: EvaluationData | None = None, log: Log | None = _stderr
) -> EvaluationResult:
    """Measure every (method, factor) cell and the full-resolution baseline.

    Args:
        config: the configuration (see :mod:`evdown_torch.config`).
        data: the recordings; by default those :func:`load_data` loads for ``config.data``.
        log: receives one progress line per step (default: stderr); ``None`` for silence.

    Returns:
        The :class:`EvaluationResult`, baseline first, then the methods in order, each with
        its factors in order.
    """
    progress = _Progress(log)
    device = _resolve_device(config.training.device)
    threads = torch.get_num_threads()
    if config.training.num_threads:
        torch.set_num_threads(config.training.num_threads)
    try:
        if data is None:
            data = load_data(config.data, progress)
        progress(f"data: {data.description}; {len(data.train)} train and {len(data.test)} "
                 f"test recordings, {data.num_classes} classes; training on {device}")
        used_threads = torch.get_num_threads()
        cells = [_cell(BASELINE, (1, 1), data, config, device, None, progress)]
        bins = config.data.time_bins
        for factor in config.methods.factors:
            pair = (factor, factor) if isinstance(factor, int) else tuple(factor)
            out_sensor = make_method("downsample", data.sensor_size, pair).output_sensor_size
            ground_truth = _ground_truth_frames(data, pair, out_sensor, bins)
            if ground_truth is not None:
                progress(f"ground truth x{_factor_text(pair)}: {len(ground_truth)} test "
                         "recordings rendered")
            for name in config.methods.names:
                cells.append(_cell(name, pair, data, config, device, ground_truth, progress))
    finally:
        torch.set_num_threads(threads)
    cells = [cells[0]] + sorted(
        cells[1:], key=lambda c: (config.methods.names.index(c.method),
                                  _factor_order(config, c.factor))
    )
    wall = time.perf_counter() - progress.start
    progress(f"done: {len(cells)} cells in {wall:.0f} s")
    return EvaluationResult(config, data.description, tuple(cells), wall, used_threads)


def _factor_order(config: EvaluationConfig, factor: tuple[int, int]) -> int:
    pairs = [(f, f) if isinstance(f, int) else tuple(f) for f in config.methods.factors]
    return pairs.index(factor)


def _factor_text(factor: tuple[int, int]) -> str:
    return str(factor[0]) if factor[0] == factor[1] else f"{factor[0]}x{factor[1]}"


# ----------------------------------------------------------------------------- report

CSV_COLUMNS = (
    "method", "factor_x", "factor_y", "width", "height", "accuracy_mean", "accuracy_std",
    "accuracies", "events_per_sample", "reduction", "throughput_events_per_s", "density",
    "entropy", "consistency", "rate_vs_ground_truth", "downscale_seconds", "train_seconds",
)


def _optional(value: float | None, fmt: str) -> str:
    return "n/a" if value is None else format(value, fmt)


def _csv_rows(result: EvaluationResult) -> list[dict[str, str]]:
    rows = []
    for c in result.cells:
        rows.append({
            "method": c.method,
            "factor_x": str(c.factor[0]),
            "factor_y": str(c.factor[1]),
            "width": str(c.output_size[0]),
            "height": str(c.output_size[1]),
            "accuracy_mean": f"{c.accuracy_mean:.4f}",
            "accuracy_std": f"{c.accuracy_std:.4f}",
            "accuracies": ";".join(f"{a:.4f}" for a in c.accuracies),
            "events_per_sample": f"{c.events_per_sample:.1f}",
            "reduction": f"{c.reduction:.4f}",
            "throughput_events_per_s": "" if c.throughput is None else f"{c.throughput:.0f}",
            "density": f"{c.density:.6g}",
            "entropy": f"{c.entropy:.6g}",
            "consistency": "" if c.consistency is None else f"{c.consistency:.4f}",
            "rate_vs_ground_truth": ""
            if c.rate_vs_ground_truth is None else f"{c.rate_vs_ground_truth:.4f}",
            "downscale_seconds": f"{c.downscale_seconds:.3f}",
            "train_seconds": f"{c.train_seconds:.1f}",
        })
    return rows


def markdown_table(result: EvaluationResult) -> str:
    """The results as a Markdown table, one row per cell."""
    lines = [
        "| method | factor | output | accuracy | events/sample | reduction | "
        "throughput (M ev/s) | density (ev/px/s) | entropy (bits) | consistency |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in result.cells:
        accuracy = f"{c.accuracy_mean:.3f}"
        if len(c.accuracies) > 1:
            accuracy += f" ± {c.accuracy_std:.3f}"
        throughput = "–" if c.throughput is None else f"{c.throughput / 1e6:.2f}"
        lines.append(
            f"| {c.method} | {_factor_text(c.factor)} | {c.output_size[0]}x{c.output_size[1]} "
            f"| {accuracy} | {c.events_per_sample:,.0f} | {c.reduction:.2f} | {throughput} "
            f"| {c.density * 1e6:.3g} | {c.entropy:.2e} | {_optional(c.consistency, '.3f')} |"
        )
    return "\n".join(lines) + "\n"


def _markdown(result: EvaluationResult) -> str:
    config = result.config
    seeds = ", ".join(str(s) for s in config.training.seeds)
    model = config.model
    return (
        f"# evdown evaluate: {config.name}\n\n"
        f"Data: {result.description}; {config.data.time_bins} time bins per recording. "
        f"Classifier: SpikingClassifier(channels={list(model.channels)}, "
        f"pool_size={model.pool_size}, beta={model.beta:g}), "
        f"{config.training.epochs} epochs, batch {config.training.batch_size}, "
        f"learning rate {config.training.learning_rate:g}, {config.training.encoding} input, "
        f"seed(s) {seeds}. Wall time {result.wall_seconds:.0f} s on {result.threads} torch "
        "thread(s).\n\n"
        + markdown_table(result)
        + "\n"
        "accuracy: test accuracy (mean ± standard deviation over the seeds); events/sample: "
        "mean output events per recording; reduction: input events / output events; "
        "throughput: input events downscaled per second; density: the paper's temporal "
        "density in events per pixel per second; entropy: the paper's information entropy "
        "per pixel and polarity; consistency: cosine similarity of per-polarity, time-binned "
        "event counts with a camera of the output resolution (the synthetic generator's "
        "ground truth), 1 = same pattern, n/a without ground truth.\n"
    )


def _plot(result: EvaluationResult, path: Path) -> bool:
    """Accuracy against throughput and against reduction; False without matplotlib."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ModuleNotFoundError:
        return False
    figure = Figure(figsize=(11, 4.5), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(1, 2, sharey=True)
    baseline = result.cells[0]
    methods = list(dict.fromkeys(c.method for c in result.cells[1:]))
    factors = list(dict.fromkeys(c.factor for c in result.cells[1:]))
    markers = "osD^v<>p*h"
    colours = [f"C{i}" for i in range(10)]
    for ax, key, label in (
        (axes[0], "throughput", "downscaling throughput (events/s)"),
        (axes[1], "reduction", "event reduction (input events / output events)"),
    ):
        for c in result.cells[1:]:
            x = getattr(c, key)
            if x is None or not math.isfinite(x) or x <= 0:
                continue
            m = methods.index(c.method)
            ax.errorbar(
                x, c.accuracy_mean, yerr=c.accuracy_std or None,
                marker=markers[factors.index(c.factor) % len(markers)],
                color=colours[m % len(colours)], linestyle="none", markersize=7, capsize=3,
            )
        ax.axhline(baseline.accuracy_mean, color="grey", linestyle="--", linewidth=1)
        ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("test accuracy")
    handles = [
        axes[0].plot([], [], color=colours[i % len(colours)], marker="o", linestyle="none",
                     label=name)[0]
        for i, name in enumerate(methods)
    ]
    handles += [
        axes[0].plot([], [], color="black", marker=markers[i % len(markers)], linestyle="none",
                     label=f"factor {_factor_text(f)}")[0]
        for i, f in enumerate(factors)
    ]
    handles.append(axes[0].plot([], [], color="grey", linestyle="--",
                                label=f"{BASELINE} ({baseline.accuracy_mean:.3f})")[0])
    figure.legend(handles=handles, loc="outside right center", frameon=False)
    figure.suptitle(f"evdown evaluate: {result.config.name} ({result.description})",
                    fontsize=10)
    figure.savefig(path, dpi=120)
    return True


def write_report(
    result: EvaluationResult, directory: str | Path, log: Log | None = _stderr
) -> dict[str, Path]:
    """Write ``results.csv``, ``report.md`` and ``tradeoff.png`` into ``directory``.

    Args:
        result: what :func:`run_evaluation` returned.
        directory: created if needed; existing files of these names are replaced.
        log: told where the files went, and when the plot is skipped for want of matplotlib.

    Returns:
        ``{"csv": ..., "markdown": ..., "plot": ...}`` for the files written (no ``"plot"``
        without matplotlib).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = {"csv": directory / "results.csv", "markdown": directory / "report.md"}
    with paths["csv"].open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        writer.writerows(_csv_rows(result))
    paths["markdown"].write_text(_markdown(result), encoding="utf-8")
    plot = directory / "tradeoff.png"
    if _plot(result, plot):
        paths["plot"] = plot
    elif log is not None:
        log("matplotlib is not installed: skipped tradeoff.png "
            "(pip install matplotlib, or evdown_torch[plot])")
    if log is not None:
        log("wrote " + ", ".join(str(p) for p in paths.values()))
    return paths
