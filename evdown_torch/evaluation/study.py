"""The study: plan the cells, fill them through worker processes, and measure them.

:func:`run_evaluation` runs these stages, each a batch of jobs (:mod:`.cells`) over a pool of
worker processes (and, under ``torchrun``, shared out among the ranks: :mod:`.ranks`), each
reading what an earlier run cached:

1. generate the recordings (synthetic data), and the low-resolution camera's renders of the
   calibration and test recordings at every factor;
2. plan the cells (:mod:`.plan`: the primary family, its control, the sanity rows, the
   exploratory cells) and calibrate each budget on the first training recordings only;
3. downscale every recording of every cell into frames, measuring the streams (a job reads
   a chunk of recordings once for all the cells of one factor; the control once per seed's
   thinning draw);
4. choose each factor's learning rate on the validation split of the training pool;
5. train and test the classifier once per seed and cell, each seed on its own draw of
   training recordings;
6. time each transform on one idle thread, in this process, after the workers are gone;
7. compare (:mod:`.analysis`): the primary family one-sided with Holm's correction and its
   two halves of seeds, the sanity check, the exploratory intervals and equivalence tests.

With ``data.folds`` (repeated stratified k-fold cross-validation of the pooled recordings)
stages 2-5 run once per ``(repeat, fold)``, each fold's training recordings standing for the
training split (calibration, the learning rate's validation split) and its test fold for the
test split; every method shares the folds and the training seeds, and :func:`.folds.pool_folds`
merges each cell's folds before the comparisons.
"""

from __future__ import annotations

import multiprocessing
import socket
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from typing import Any, cast

import torch
from tqdm import tqdm

from evdown_torch.distributed import all_gather, barrier, broadcast, local_rank, rank_and_world
from evdown_torch.evaluation import cells as jobs
from evdown_torch.evaluation import classifier
from evdown_torch.evaluation.analysis import Comparison
from evdown_torch.evaluation.cache import Cache
from evdown_torch.evaluation.cells import Cell
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.data import POOLED, StudyData, check_available
from evdown_torch.evaluation.folds import pool_folds
from evdown_torch.evaluation.measure import Filled, measure_cells
from evdown_torch.evaluation.plan import (
    Planned,
    pair,
    plan,
    selection_cells,
)
from evdown_torch.evaluation.ranks import (
    EVERY_GROUP,
    Ranks,
    Stage,
    cell_groups,
    check_agreement,
    claim_cache,
    downscale_seconds,
    release,
    seed_recordings,
    training_seconds,
)
from evdown_torch.evaluation.results import CellResult, EvaluationResult, RankRun
from evdown_torch.evaluation.verdicts import compare_cells

__all__ = ["CellResult", "Comparison", "EvaluationResult", "RankRun", "run_evaluation"]

Log = Callable[[str], None]
CHUNK = 24  # recordings per downscaling job


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


def _resolve_device(name: str, world: int = 1) -> torch.device:
    """The device of ``training.device``.

    Of ``world`` ranks, ``"auto"`` and ``"cuda"`` take the GPU of the rank's ``LOCAL_RANK``
    (modulo the GPUs present); ``"auto"`` takes the CPU without CUDA.
    """
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"training.device {name!r} is not a torch device") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"training.device is {name!r} but CUDA is not available here")
    if device.type == "cuda" and device.index is None and world > 1:
        device = torch.device("cuda", local_rank() % torch.cuda.device_count())
    return device


def _chunks(indices: range, size: int = CHUNK) -> list[list[int]]:
    return [list(indices[i:i + size]) for i in range(0, len(indices), size)]


def _consistency_recordings(config: EvaluationConfig, source: StudyData) -> int:
    """How many test recordings (the first ones) are compared with the camera."""
    n = source.size("test")
    return min(config.measures.consistency_recordings or n, n)


def _cpu_seconds() -> float:
    """CPU seconds of this process and of its finished children (the workers).

    This process alone where the platform cannot say (Windows).
    """
    try:
        import resource
    except ModuleNotFoundError:  # pragma: no cover - Windows
        return time.process_time()
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(
        resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def run_evaluation(
    config: EvaluationConfig, *, log: Log | None = _stderr, cache: bool = True
) -> EvaluationResult:
    """Run the study of ``config`` and measure every cell.

    Args:
        config: the configuration (see :mod:`evdown_torch.evaluation.config`).
        log: receives progress lines (default: stderr, with a progress bar per long stage);
            ``None`` for silence. Rank 0's only, under ``torch.distributed``.
        cache: reuse and keep what is cached under ``config.output.cache``; ``False`` works
            in a temporary directory removed at the end.

    Returns:
        The :class:`EvaluationResult` (the same on every rank).

    With ``training.workers > 0`` the stages run in spawned worker processes, which import
    the calling script again: call this from under ``if __name__ == "__main__":``. Under an
    initialised ``torch.distributed`` process group (``evdown evaluate`` under ``torchrun``
    joins one) every rank calls this: the ranks share out each stage's jobs, each with its own
    workers and device (:mod:`.ranks`), and rank 0 times the transforms and measures.

    Raises:
        FileNotFoundError: for DVS128 Gesture absent from its root.
        RuntimeError: if a needed optional package (tonic) is missing.
        ValueError: where the ranks hold different configs, or the cache holds an unfinished
            run of this study under another config.
    """
    rank, world = rank_and_world()
    progress = _Progress(log if rank == 0 else None)
    cpu_start = _cpu_seconds()
    check_agreement(config)
    if rank == 0:  # first, alone: it may download the dataset
        check_available(config.data)
    barrier()
    if rank != 0:
        check_available(config.data)
    device = _resolve_device(config.training.device, world)
    store = Cache(config.output.cache if cache else None)
    ranks = Ranks(store.root)
    record = claim_cache(store, config, ranks)
    if world > 1:
        progress(ranks.describe())
    sources = [StudyData(config.data, str(store.root), unit if config.data.folds else None)
               for unit in config.data.fold_units]
    source = sources[0]
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
        every_fold = []
        for fold_source in sources:
            if fold_source.fold is not None:
                progress(f"repeat {fold_source.fold[0]}, fold {fold_source.fold[1]}: "
                         f"{fold_source.size('train')} training, {fold_source.size('test')} "
                         "test recordings")
            every_fold.append(_fill(config, fold_source, pool, ranks, device, progress))
    finally:
        pool.shutdown()
    filled = every_fold[0]
    generated = sum(f.generated for f in every_fold)
    mine = RankRun(rank, socket.gethostname(), str(device), ranks.jobs, generated,
                   time.perf_counter() - progress.start, _cpu_seconds() - cpu_start)
    every = all_gather(mine)
    result = None
    try:
        if rank == 0:
            torch.set_num_threads(1)
            speeds = {p.cell: jobs.throughput(source, p.cell,
                                              config.measures.throughput_recordings)
                      for p in filled.planned}
            progress("timed every transform on one thread")
            # timed on the first fold's cells (each fold calibrates its own settings)
            per_fold = [measure_cells(config, s, f, {p.cell: speeds[q.cell] for p, q in
                                                zip(f.planned, filled.planned)})
                        for s, f in zip(sources, every_fold)]
            results = (pool_folds(per_fold, sources, config) if config.data.folds
                       else per_fold[0])
    finally:
        torch.set_num_threads(threads)
        store.close()
    if rank == 0:
        results, sanity, noninferior = compare_cells(results, config)
        every[0] = replace(mine, wall_seconds=time.perf_counter() - progress.start,
                           cpu_seconds=_cpu_seconds() - cpu_start)
        wall, cpu = every[0].wall_seconds, sum(r.cpu_seconds for r in every)
        generated = sum(r.generated for r in every)
        progress(f"done: {len(results)} cells in {wall:.0f} s, {cpu:.0f} CPU s "
                 f"({generated} recordings or renders generated)")
        result = EvaluationResult(
            config, source.description(), tuple(results), filled.rates, sanity, wall, cpu,
            training.workers, generated, str(device) if world == 1 else device.type,
            tuple(every) if world > 1 else (), ranks.gathered_through, noninferior)
    result = broadcast(result)
    release(record)
    return cast(EvaluationResult, result)


def _map(pool: Any, ranks: Ranks, progress: _Progress, what: str, fn: Callable,
         *columns: list, costs: list[float] | None = None,
         where: Sequence[int] | str | None = None, gather: bool = True) -> Stage:
    """A stage: this rank's jobs of ``fn`` over ``columns``, then every job's result.

    This rank's jobs (:meth:`Ranks.runners`, by ``costs``: 1 per job by default) run through
    ``pool``, with a progress bar to stderr while logging; then :meth:`Ranks.gather`.
    """
    n = len(columns[0])
    runners = ranks.runners([1.0] * n if costs is None else costs, where)
    here = [j for j in range(n) if ranks.rank in runners[j]]
    out = pool.map(fn, *([column[j] for j in here] for column in columns))
    if progress.log is not None:
        out = tqdm(out, total=len(here), desc=what, unit="job", file=sys.stderr,
                   leave=False, mininterval=2.0)
    mine = dict(zip(here, out))
    ranks.jobs += len(here)
    return Stage(ranks.gather(fn, columns, runners, mine, gather), here)


def _fill(config: EvaluationConfig, source: StudyData, pool: Any, ranks: Ranks,
          device: torch.device, progress: _Progress) -> Filled:
    for split in ("train", "test"):
        if not source.size(split):
            raise ValueError(f"the {split} split has no recordings")
    # the splits whose frames are made: under cross-validation every pooled recording once,
    # shared by the folds (a fold's splits are rows of it), else the train and test splits
    framed = (POOLED,) if source.fold is not None else ("train", "test")
    chunks = {s: _chunks(range(source.size(s))) for s in framed}
    calibrate_on = source.calibration_split
    calibration_samples = min(config.data.calibration_samples, source.size(calibrate_on))
    generated = 0
    by = " by rank 0" if ranks.world > 1 else ""  # whose generation the log counts
    factors = [pair(f) for f in config.methods.all_factors]
    if source.synthetic:
        splits = [s for s in ("train", "test") for _ in chunks[s]]
        parts = chunks["train"] + chunks["test"]
        stage = _map(pool, ranks, progress, "recordings", jobs.generate_job,
                     [source] * len(splits), splits, parts, costs=[len(p) for p in parts],
                     where=EVERY_GROUP, gather=False)
        generated += sum(stage.results[j][0] for j in stage.here)
        progress(f"recordings: {source.size('train')} train and {source.size('test')} test "
                 f"({generated} generated{by})")
    camera: dict[tuple[int, int], int] = {}
    if source.has_ground_truth:
        measured = _chunks(range(_consistency_recordings(config, source)))
        renders = [(s, c, f) for f in factors
                   for s, c in [("train", list(range(calibration_samples)))]
                   + [("test", c) for c in measured]]
        stage = _map(pool, ranks, progress, "camera renders", jobs.generate_job,
                     [source] * len(renders), [r[0] for r in renders], [r[1] for r in renders],
                     [r[2] for r in renders], costs=[len(r[1]) for r in renders],
                     where=EVERY_GROUP)
        made = sum(stage.results[j][0] for j in stage.here)
        generated += made
        for (split, _, factor), (_, counts) in zip(renders, stage.results):
            if split == "train":
                camera[factor] = sum(counts)
        progress(f"low-resolution camera renders at x{', x'.join(str(f[0]) for f in camera)} "
                 f"({made} generated{by})")
    planned, found = _calibrate(config, source, pool, ranks, plan(config), camera,
                                calibrate_on, calibration_samples, progress)
    selection = selection_cells(config, planned)
    group = cell_groups(config, ranks, planned, selection, source.size("train"),
                        source.size("test"))
    # One job per factor, split and chunk (and group of ranks): it reads the chunk's
    # recordings once for every unit (a cell and, for the control, each seed's thinning draw)
    # of that factor.
    by_factor: dict[tuple[tuple[int, int], int], list[tuple[Cell, int]]] = {}
    for p in planned:
        for draw in (p.seeds if p.cell.random else (0,)):
            by_factor.setdefault((p.cell.factor, group[p.cell]), []).append((p.cell, draw))
    work = [(units, s, part, g) for (_, g), units in by_factor.items() for s in framed
            for part in chunks[s]]
    out = _map(pool, ranks, progress, "downscaling", jobs.downscale_job, [source] * len(work),
               [w[0] for w in work], [w[1] for w in work], [w[2] for w in work],
               [config] * len(work),
               costs=[downscale_seconds(config, [c for c, _ in w[0]], len(w[2])) for w in work],
               where=[w[3] for w in work]).results
    stats: dict[Cell, dict[str, dict[str, list[float]]]] = {
        p.cell: {s: {} for s in framed} for p in planned}
    for (units, split, _, _), parts in zip(work, out):
        first = jobs.measured_draws(units)
        for (cell, draw), part in zip(units, parts):
            if draw == first[cell]:
                for k, values in part.items():
                    stats[cell][split].setdefault(k, []).extend(values)
    if source.fold is not None:
        stats = {cell: {s: _rows_of(by_split[POOLED], source.positions(s), source.pooled_size)
                        for s in ("train", "test")} for cell, by_split in stats.items()}
    progress(f"downscaled every recording for {len(planned)} cells "
             f"({sum(len(u) for u in by_factor.values())} with the control's draws)")
    trainer = pool if device.type == "cpu" else _Inline()
    rates = _choose_rates(config, source, trainer, ranks, planned, selection, group, chunks,
                          device, progress)
    runs = [(p.cell, seed) for p in planned for seed in p.seeds]
    cost = {p.cell: training_seconds(config, p.cell, seed_recordings(config, source.size("train")),
                                     source.size("test")) for p in planned}
    out = _map(trainer, ranks, progress, "training", classifier.train_job, [source] * len(runs),
               [r[0] for r in runs], [chunks] * len(runs), [config] * len(runs),
               [r[1] for r in runs], [str(device)] * len(runs),
               [rates[r[0].factor][0] for r in runs],
               costs=[cost[r[0]] for r in runs], where=[group[r[0]] for r in runs]).results
    predictions: dict[Cell, dict[int, dict[str, Any]]] = {p.cell: {} for p in planned}
    for (cell, seed), result in zip(runs, out):
        predictions[cell][seed] = result
    for p in planned:
        accuracies = [sum(r["correct"]) / len(r["correct"]) for r in predictions[p.cell].values()]
        progress(f"{p.cell.label} ({p.role}): accuracy {statistics.fmean(accuracies):.3f} over "
                 f"{len(accuracies)} seed(s)")
    return Filled(planned, stats, predictions, found, rates, generated)


def _rows_of(measures: dict[str, list[float]], rows: Sequence[int], pooled: int
             ) -> dict[str, list[float]]:
    """Per-recording ``measures`` of the ``pooled`` recordings, taken at ``rows`` (a fold's split).

    Measures kept for no recording (an empty list) stay empty.

    Raises:
        RuntimeError: for a measure kept for some recordings only (it cannot be split).
    """
    partial = [k for k, values in measures.items() if values and len(values) != pooled]
    if partial:
        raise RuntimeError(f"the measures {partial} cover some of the {pooled} pooled "
                           "recordings only, so a fold's share of them is unknown")
    return {k: [values[i] for i in rows] if values else [] for k, values in measures.items()}


def _choose_rates(config: EvaluationConfig, source: StudyData, trainer: Any, ranks: Ranks,
                  planned: list[Planned], selection: dict[tuple[int, int], Cell],
                  group: dict[Cell, int], chunks: dict, device: torch.device,
                  progress: _Progress) -> dict[tuple[int, int], tuple[float, dict]]:
    """The learning rate of each factor, chosen on the validation split of the training pool.

    Each candidate of ``training.learning_rates`` trains the factor's selection cell
    (:func:`~evdown_torch.evaluation.plan.selection_cells`; in its ``group`` of ranks) on
    ``training.selection_seeds`` seeds, on draws from the pool less its first
    ``data.validation_samples`` recordings, and is scored on those; the best mean accuracy
    wins (ties: the smaller rate). The test split is never read. Without candidates every
    factor uses ``training.learning_rate``.
    """
    training = config.training
    factors = list(dict.fromkeys(p.cell.factor for p in planned))
    if not training.learning_rates or not config.data.validation_samples:
        return {f: (training.learning_rate, {}) for f in factors}
    chosen = {}
    runs = [(f, rate, seed) for f in factors for rate in training.learning_rates
            for seed in range(training.selection_seeds)]
    cost = {f: training_seconds(config, selection[f],
                                seed_recordings(config, source.size("train"), True),
                                config.data.validation_samples) for f in factors}
    out = _map(trainer, ranks, progress, "learning rates", classifier.train_job,
               [source] * len(runs), [selection[r[0]] for r in runs], [chunks] * len(runs),
               [config] * len(runs), [r[2] for r in runs], [str(device)] * len(runs),
               [r[1] for r in runs], [True] * len(runs),
               costs=[cost[r[0]] for r in runs], where=[group[selection[r[0]]] for r in runs]
               ).results
    scores: dict[tuple[int, int], dict[float, list[float]]] = {f: {} for f in factors}
    for (f, rate, _), result in zip(runs, out):
        scores[f].setdefault(rate, []).append(sum(result["correct"]) / len(result["correct"]))
    for f in factors:
        means = {rate: statistics.fmean(v) for rate, v in scores[f].items()}
        best = max(sorted(means), key=lambda rate: means[rate])
        chosen[f] = (best, means)
        progress(f"x{f[0]}: learning rate {best:g} on {config.data.validation_samples} "
                 f"validation recordings ({selection[f].label}: " + ", ".join(
                     f"{rate:g} -> {m:.3f}" for rate, m in means.items()) + ")")
    return chosen


def _calibrate(config: EvaluationConfig, source: StudyData, pool: Any, ranks: Ranks,
               planned: list[Planned], camera: dict[tuple[int, int], int], split: str,
               samples: int, progress: _Progress
               ) -> tuple[list[Planned], dict[Cell, dict[str, Any]]]:
    """Calibrate every budgeted cell on the first ``samples`` recordings of ``split``.

    ``split`` is ``"train"`` or the held-out ``"calibration"`` split (the same in every fold,
    so the folds after the first read the calibrations from the cache).
    """
    todo = [i for i, p in enumerate(planned) if p.cell.budget is not None]
    matched = [i for i, p in enumerate(planned) if p.cell.matches is not None]
    if not todo and not matched:
        return planned, {}
    if config.methods.budget_reference == "input":
        inputs = sum(len(source.recording(split, i)[0]) for i in range(samples))
    targets = [cast(float, planned[i].cell.budget)
               * (camera[planned[i].cell.factor] if config.methods.budget_reference == "camera"
                  else inputs)
               for i in todo]
    # a matched control's target: its peer's output count on the same recordings
    peers = [Cell(cast(str, planned[i].cell.matches), planned[i].cell.factor) for i in matched]
    targets += [float(n) for n in _map(
        pool, ranks, progress, "matched counts", jobs.output_count_job, [source] * len(peers),
        peers, [samples] * len(peers), [split] * len(peers),
        costs=[downscale_seconds(config, [peer], samples) for peer in peers]).results]
    todo += matched
    # a cell trained with another classifier (robustness) has the same calibration: once
    bases = [(replace(planned[i].cell, classifier=()), target) for i, target in zip(todo, targets)]
    searches = list(dict.fromkeys(bases))
    out = dict(zip(searches, _map(
        pool, ranks, progress, "calibration", jobs.calibrate_job, [source] * len(searches),
        [c for c, _ in searches], [t for _, t in searches], [samples] * len(searches),
        [split] * len(searches),
        costs=[downscale_seconds(config, [c], samples) for c, _ in searches]).results))
    cells, found = list(planned), {}
    for i, base in zip(todo, bases):
        cell, search = out[base]
        cell = replace(cell, classifier=planned[i].cell.classifier)
        cells[i], found[cell] = replace(planned[i], cell=cell), search
    where = "held-out" if split != "train" else "training"
    progress(f"calibrated {len(todo)} budgeted or matched cells on {samples} {where} "
             "recordings")
    return cells, found
