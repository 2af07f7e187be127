"""The study: plan the cells, fill them through worker processes, and measure them.

:func:`run_evaluation` runs these stages, each a batch of jobs (:mod:`.cells`) over a pool of
worker processes, each reading what an earlier run cached:

1. generate the recordings (synthetic data), and the low-resolution camera's renders of the
   calibration and test recordings at every factor;
2. plan the cells: the full-resolution baseline; per factor, every method without a budget
   setting at its settings (Downsample, EventFunnelling), every method with one at each budget
   (calibrated on the first training recordings only), and the thinning control at each budget;
3. downscale every recording of every cell into frames, measuring the streams (a job reads
   a chunk of recordings once for all the cells of one factor);
4. train and test the classifier once per seed and cell;
5. time each transform on one idle thread, in this process, after the workers are gone;
6. compute the intervals and the paired tests against the control, Holm-corrected.
"""

from __future__ import annotations

import math
import multiprocessing
import statistics
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import torch

from evdown_torch.config import EvaluationConfig
from evdown_torch.evaluation import cells as jobs
from evdown_torch.evaluation.cache import Cache
from evdown_torch.evaluation.cells import BASELINE, CONTROL, Cell, model_for
from evdown_torch.evaluation.data import Source, check_available
from evdown_torch.evaluation.statistics import bootstrap_interval, holm, paired_bootstrap
from evdown_torch.transforms.registry import METHODS

__all__ = ["CellResult", "Comparison", "EvaluationResult", "run_evaluation"]

Log = Callable[[str], None]
CHUNK = 24  # recordings per downscaling job


@dataclass(frozen=True)
class Comparison:
    """A cell against the thinning control at the same factor and budget.

    Attributes:
        difference: accuracy of the cell minus the control's (same test recordings, seeds).
        p_value: two-sided paired-bootstrap p-value.
        p_holm: Holm-adjusted over every comparison of the study.
        significant: ``p_holm < alpha``.
    """

    difference: float
    p_value: float
    p_holm: float
    significant: bool


@dataclass(frozen=True)
class CellResult:
    """The measurements of one cell (test split unless said otherwise).

    Attributes:
        cell: the :class:`~evdown_torch.evaluation.cells.Cell`.
        output_size: ``(W, H)`` of the frames.
        seeds: training seeds.
        correct: per seed, per test recording: classified correctly.
        accuracy: mean of ``correct``.
        interval: bootstrap confidence interval of the accuracy (recordings and seeds).
        events_per_recording: mean output events per recording.
        events_per_second: output events per second of recording.
        reduction: input events / output events.
        rate_vs_camera: output events / the low-resolution camera's events; ``None`` without
            ground truth (1 for the baseline).
        consistency: mean optical consistency with the camera (:func:`~evdown_torch.metrics.
            optical_consistency`); ``None`` without ground truth and for the baseline.
        density, entropy: the paper's measures, mean per recording.
        throughput: input events per second of the transform on one idle thread.
        macs_per_recording: the classifier's multiply-accumulates per recording (dense).
        synops_per_recording: synaptic operations of the classifier's first layer, output
            events times their fan-out.
        calibration: what the budget search found (``None`` without a budget).
        train_seconds: mean training time per seed.
        comparison: against the control at the same budget; ``None`` for unbudgeted cells.
    """

    cell: Cell
    output_size: tuple[int, int]
    seeds: tuple[int, ...]
    correct: tuple[tuple[bool, ...], ...]
    accuracy: float
    interval: tuple[float, float]
    events_per_recording: float
    events_per_second: float
    reduction: float
    rate_vs_camera: float | None
    consistency: float | None
    density: float
    entropy: float
    throughput: float | None
    macs_per_recording: int
    synops_per_recording: float
    calibration: dict[str, Any] | None
    train_seconds: float
    comparison: Comparison | None = None

    @property
    def method(self) -> str:
        return self.cell.method

    @property
    def factor(self) -> tuple[int, int]:
        return self.cell.factor

    @property
    def budget(self) -> float | None:
        return self.cell.budget

    @property
    def accuracies(self) -> tuple[float, ...]:
        """Test accuracy of each seed."""
        return tuple(sum(row) / len(row) for row in self.correct)


@dataclass(frozen=True)
class EvaluationResult:
    """All cells of one run and how the run went.

    Attributes:
        config: the configuration.
        description: the data, in one line.
        cells: baseline first, then per factor the methods in registry order (budgets
            ascending), then the control.
        wall_seconds: the run's wall time.
        workers: worker processes used.
        generated: recordings and renders generated (not read from the cache).
        device: where the classifier trained.
    """

    config: EvaluationConfig
    description: str
    cells: tuple[CellResult, ...]
    wall_seconds: float
    workers: int
    generated: int
    device: str


class _Progress:
    def __init__(self, log: Log | None) -> None:
        self.start = time.perf_counter()
        self.log = log

    def __call__(self, message: str) -> None:
        if self.log is not None:
            self.log(f"[{time.perf_counter() - self.start:7.1f} s] {message}")


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


class _Inline:
    """Runs jobs in this process, in order."""

    def map(self, fn: Callable, *iterables: Iterable) -> Iterable:
        return map(fn, *iterables)

    def shutdown(self) -> None:
        pass


def _worker_init(threads: int) -> None:
    torch.set_num_threads(max(threads, 1))


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


def _chunks(indices: range, size: int = CHUNK) -> list[list[int]]:
    return [list(indices[i:i + size]) for i in range(0, len(indices), size)]


def _pairs(config: EvaluationConfig) -> list[tuple[int, int]]:
    return [(f, f) if isinstance(f, int) else tuple(f) for f in config.methods.factors]


def _plan(config: EvaluationConfig) -> list[Cell]:
    """Every cell, calibration still to do (budget settings at their configured start)."""
    methods = config.methods
    planned = [Cell(BASELINE, (1, 1))]
    for factor in _pairs(config):
        for name in methods.names:
            settings = tuple(sorted(config.method_settings(name).items()))
            if METHODS[name].budget_setting is None or not methods.budgets:
                planned.append(Cell(name, factor, None, settings))
            else:
                planned += [Cell(name, factor, b, settings) for b in methods.budgets]
        if methods.control and methods.budgets:
            planned += [Cell(CONTROL, factor, b) for b in methods.budgets]
    return planned


def run_evaluation(
    config: EvaluationConfig, *, log: Log | None = _stderr, cache: bool = True
) -> EvaluationResult:
    """Run the study of ``config`` and measure every cell.

    Args:
        config: the configuration (see :mod:`evdown_torch.config`).
        log: receives one progress line per step (default: stderr); ``None`` for silence.
        cache: reuse and keep what is cached under ``config.output.cache``; ``False`` works
            in a temporary directory removed at the end.

    Returns:
        The :class:`EvaluationResult`.

    With ``training.workers > 0`` the stages run in spawned worker processes, which import
    the calling script again: call this from under ``if __name__ == "__main__":``.

    Raises:
        FileNotFoundError: for DVS128 Gesture absent from its root.
        RuntimeError: if a needed optional package (tonic) is missing.
    """
    progress = _Progress(log)
    check_available(config.data)
    device = _resolve_device(config.training.device)
    store = Cache(config.output.cache if cache else None)
    source = Source(config.data, str(store.root))
    training = config.training
    threads = torch.get_num_threads()
    if training.num_threads:
        torch.set_num_threads(training.num_threads)
    pool: Any = _Inline()
    if training.workers:
        pool = ProcessPoolExecutor(
            training.workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=_worker_init, initargs=(training.num_threads,))
    try:
        cells, stats, predictions, found, generated = _fill(config, source, pool, device, progress)
    finally:
        pool.shutdown()
    try:
        torch.set_num_threads(1)
        speeds = {c: jobs.throughput(source, c, config.measures.throughput_recordings)
                  for c in cells}
        progress("timed every transform on one thread")
        results = _measure(config, source, cells, stats, predictions, found, speeds)
    finally:
        torch.set_num_threads(threads)
        store.close()
    wall = time.perf_counter() - progress.start
    progress(f"done: {len(results)} cells in {wall:.0f} s ({generated} recordings or renders "
             "generated)")
    return EvaluationResult(config, source.description(), tuple(results), wall,
                            training.workers, generated, str(device))


def _fill(config: EvaluationConfig, source: Source, pool: Any, device: torch.device,
          progress: _Progress) -> tuple[list[Cell], dict, dict, dict, int]:
    chunks = {s: _chunks(range(source.size(s))) for s in ("train", "test")}
    for split, parts in chunks.items():
        if not parts:
            raise ValueError(f"the {split} split has no recordings")
    calibration_samples = min(config.data.calibration_samples, source.size("train"))
    generated = 0
    if source.synthetic:
        splits = [s for s in ("train", "test") for _ in chunks[s]]
        out = list(pool.map(jobs.generate_job, [source] * len(splits), splits,
                            chunks["train"] + chunks["test"]))
        generated += sum(g for g, _ in out)
        progress(f"recordings: {source.size('train')} train and {source.size('test')} test "
                 f"({generated} generated)")
    camera: dict[tuple[int, int], int] = {}
    if source.has_ground_truth:
        renders = [(s, c, f) for f in _pairs(config)
                   for s, c in [("train", list(range(calibration_samples)))]
                   + [("test", c) for c in chunks["test"]]]
        out = list(pool.map(jobs.generate_job, [source] * len(renders),
                            [r[0] for r in renders], [r[1] for r in renders],
                            [r[2] for r in renders]))
        made = sum(g for g, _ in out)
        generated += made
        for (split, _, factor), (_, counts) in zip(renders, out):
            if split == "train":
                camera[factor] = sum(counts)
        progress(f"low-resolution camera renders at x{', x'.join(str(f[0]) for f in camera)} "
                 f"({made} generated)")
    planned = _plan(config)
    cells, found = _calibrate(config, source, pool, planned, camera, calibration_samples,
                              progress)
    # One job per factor, split and chunk: it reads the chunk's recordings once for the cells.
    by_factor: dict[tuple[int, int], list[Cell]] = {}
    for c in cells:
        by_factor.setdefault(c.factor, []).append(c)
    work = [(group, s, part) for group in by_factor.values() for s in ("train", "test")
            for part in chunks[s]]
    out = list(pool.map(jobs.downscale_job, [source] * len(work), [w[0] for w in work],
                        [w[1] for w in work], [w[2] for w in work], [config] * len(work)))
    stats: dict[Cell, dict[str, dict[str, list[float]]]] = {c: {"train": {}, "test": {}}
                                                            for c in cells}
    for (group, split, _), parts in zip(work, out):
        for cell, part in zip(group, parts):
            for k, values in part.items():
                stats[cell][split].setdefault(k, []).extend(values)
    progress(f"downscaled every recording for {len(cells)} cells")
    runs = [(c, seed) for c in cells
            for seed in (config.training.baseline_seeds if c.method == BASELINE
                         else config.training.seeds)]
    trainer = pool if device.type == "cpu" else _Inline()
    out = trainer.map(jobs.train_job, [source] * len(runs), [r[0] for r in runs],
                      [chunks] * len(runs), [config] * len(runs), [r[1] for r in runs],
                      [str(device)] * len(runs))
    predictions: dict[Cell, dict[int, dict[str, Any]]] = {c: {} for c in cells}
    for (cell, seed), result in zip(runs, out):
        predictions[cell][seed] = result
        if len(predictions[cell]) == (len(config.training.baseline_seeds)
                                      if cell.method == BASELINE else len(config.training.seeds)):
            accuracies = [sum(r["correct"]) / len(r["correct"])
                          for r in predictions[cell].values()]
            progress(f"{cell.label}: accuracy {statistics.fmean(accuracies):.3f} over "
                     f"{len(accuracies)} seed(s)")
    return cells, stats, predictions, found, generated


def _calibrate(config: EvaluationConfig, source: Source, pool: Any, planned: list[Cell],
               camera: dict[tuple[int, int], int], samples: int, progress: _Progress
               ) -> tuple[list[Cell], dict[Cell, dict[str, Any]]]:
    """Calibrate every budgeted cell on the first ``samples`` training recordings."""
    todo = [i for i, c in enumerate(planned) if c.budget is not None]
    if not todo:
        return planned, {}
    if config.methods.budget_reference == "input":
        inputs = sum(len(source.recording("train", i)[0]) for i in range(samples))
    targets = [planned[i].budget * (camera[planned[i].factor]
                                    if config.methods.budget_reference == "camera" else inputs)
               for i in todo]
    out = list(pool.map(jobs.calibrate_job, [source] * len(todo), [planned[i] for i in todo],
                        targets, [samples] * len(todo)))
    cells, found = list(planned), {}
    for i, (cell, search) in zip(todo, out):
        cells[i], found[cell] = cell, search
    progress(f"calibrated {len(todo)} budgeted cells on {samples} training recordings")
    return cells, found


def _measure(config: EvaluationConfig, source: Source, cells: list[Cell], stats: dict,
             predictions: dict, found: dict, speeds: dict) -> list[CellResult]:
    sensor = source.sensor_size
    st = config.statistics
    results = []
    for cell in cells:
        test = stats[cell]["test"]
        seeds = tuple(sorted(predictions[cell]))
        correct = tuple(tuple(predictions[cell][s]["correct"]) for s in seeds)
        matrix = torch.tensor(correct, dtype=torch.bool)
        w, h, _ = cell.output_size(sensor)
        model = model_for(config, (w, h), source.num_classes)
        n = len(test["events_out"])
        out_total, in_total = sum(test["events_out"]), sum(test["events_in"])
        fan_out = (model.stem_channels if model.stem is not None else model.channels[0] * 9)
        camera = None
        if source.has_ground_truth:
            camera = 1.0 if cell.method == BASELINE else (
                out_total / sum(test["camera_events"]) if sum(test["camera_events"]) else math.inf)
        results.append(CellResult(
            cell=cell,
            output_size=(w, h),
            seeds=seeds,
            correct=correct,
            accuracy=float(matrix.double().mean()),
            interval=bootstrap_interval(matrix, confidence=st.confidence,
                                        resamples=st.resamples, seed=st.seed),
            events_per_recording=out_total / n,
            events_per_second=out_total / max(sum(test["duration"]) * 1e-6, 1e-9),
            reduction=in_total / out_total if out_total else math.inf,
            rate_vs_camera=camera,
            consistency=statistics.fmean(test["consistency"]) if test["consistency"] else None,
            density=statistics.fmean(test["density"]),
            entropy=statistics.fmean(test["entropy"]),
            throughput=speeds[cell],
            macs_per_recording=model.macs_per_step(h, w) * config.data.time_bins,
            synops_per_recording=out_total / n * fan_out,
            calibration=found.get(cell),
            train_seconds=statistics.fmean(r["seconds"] for r in predictions[cell].values()),
        ))
    return _compare(results, config)


def _compare(results: list[CellResult], config: EvaluationConfig) -> list[CellResult]:
    """Each budgeted method against the control at its factor and budget, Holm-corrected."""
    st = config.statistics
    controls = {(r.factor, r.budget): r for r in results if r.method == CONTROL}
    pairs = [(i, controls[(r.factor, r.budget)]) for i, r in enumerate(results)
             if r.budget is not None and r.method != CONTROL and (r.factor, r.budget) in controls]
    tests = [paired_bootstrap(torch.tensor(results[i].correct), torch.tensor(c.correct),
                              resamples=st.resamples, seed=st.seed) for i, c in pairs]
    adjusted = holm([p for _, p in tests])
    out = list(results)
    for (i, _), (d, p), q in zip(pairs, tests, adjusted):
        out[i] = replace(out[i], comparison=Comparison(d, p, q, q < st.alpha))
    return out
