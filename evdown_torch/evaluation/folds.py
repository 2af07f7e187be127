"""Cross-validation: one cell's results on every ``(repeat, fold)`` pooled into one.

With ``data.folds`` the study runs once per repeat and fold (:mod:`.study`), every method on
the same folds and the same training seeds. :func:`pool_folds` merges a cell's per-fold
results: within a repeat every pooled recording is tested exactly once, so each ``(repeat,
seed)`` becomes one row of correctness over every recording, its columns in the pooled order
(the same recording in the same column for every repeat and cell: the pairing is kept). The
per-``(repeat, fold, seed)`` accuracies are kept as ``units`` for the corrected resampled
t-test (:func:`~evdown_torch.evaluation.statistics.corrected_resampled_t`).
"""

from __future__ import annotations

import statistics
from dataclasses import replace

import torch

from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.data import StudyData
from evdown_torch.evaluation.results import CellResult
from evdown_torch.evaluation.statistics import hierarchical_means, interval_of

__all__ = ["pool_folds"]


def _weighted(values: list[float], weights: list[int]) -> float:
    return sum(v * w for v, w in zip(values, weights)) / sum(weights)


def pool_folds(per_fold: list[list[CellResult]], sources: list[StudyData],
               config: EvaluationConfig) -> list[CellResult]:
    """Merge each cell's results over the folds of ``sources`` (one list of cells per fold).

    Args:
        per_fold: per ``(repeat, fold)``, in ``config.data.fold_units`` order, the cells in
            the plan's order (the same cells in every fold, their budget settings calibrated
            on each fold's training recordings).
        sources: the :class:`StudyData` of each fold, in the same order.
        config: the study's configuration.

    Returns:
        One :class:`CellResult` per cell: ``correct`` and ``predicted`` hold one row per
        ``(repeat, seed)`` over every pooled recording; ``units`` each ``(repeat, fold, seed)``
        with its accuracy and learning rate; the stream measures are means over the folds
        weighted by their test recordings; ``cell``, ``calibration`` and ``learning_rate``
        are the first fold's (each fold's rate is in ``units``).

    Raises:
        ValueError: if the folds disagree on the cells or their seeds.
    """
    units = config.data.fold_units
    if len(per_fold) != len(units) or len(sources) != len(units):
        raise ValueError(f"pool_folds needs {len(units)} folds, got {len(per_fold)} results "
                         f"and {len(sources)} sources")
    n = sources[0].pooled_size
    positions = [s.test_positions for s in sources]
    sizes = [len(p) for p in positions]
    st = config.statistics
    out = []
    for cells in zip(*per_fold):
        first = cells[0]
        if any(c.cell.name != first.cell.name or c.factor != first.factor
               or c.budget != first.budget or c.seeds != first.seeds for c in cells):
            raise ValueError(f"the folds disagree on the cell {first.cell.label} or its seeds")
        correct: list[list[bool]] = []
        predicted: list[list[int]] = []
        labels = [0] * n
        unit_rows = []
        for repeat in range(config.data.repeats):
            rows_c = [[False] * n for _ in first.seeds]
            rows_p = [[0] * n for _ in first.seeds]
            for k, (r, f) in enumerate(units):
                if r != repeat:
                    continue
                result = cells[k]
                for s, seed in enumerate(result.seeds):
                    for j, pos in enumerate(positions[k]):
                        rows_c[s][pos] = result.correct[s][j]
                        rows_p[s][pos] = result.predicted[s][j]
                    unit_rows.append((r, f, seed, result.accuracies[s], result.learning_rate))
                for j, pos in enumerate(positions[k]):
                    labels[pos] = result.labels[j]
            correct += rows_c
            predicted += rows_p
        matrix = torch.tensor(correct, dtype=torch.bool)
        out_events = [c.events_per_recording * w for c, w in zip(cells, sizes)]
        in_events = [c.reduction * e if e else 0.0 for c, e in zip(cells, out_events)]
        consistencies = [c.consistency for c in cells]
        out.append(replace(
            first, correct=tuple(map(tuple, correct)), predicted=tuple(map(tuple, predicted)),
            labels=tuple(labels),
            accuracy=float(matrix.double().mean()),
            interval=interval_of(hierarchical_means([matrix], resamples=st.resamples,
                                                    seed=st.seed)[:, 0],
                                 confidence=st.confidence),
            events_per_recording=sum(out_events) / sum(sizes),
            events_per_second=_weighted([c.events_per_second for c in cells], sizes),
            reduction=sum(in_events) / sum(out_events) if sum(out_events) else first.reduction,
            consistency=None if None in consistencies
            else _weighted([float(c) for c in consistencies if c is not None], sizes),
            density=_weighted([c.density for c in cells], sizes),
            entropy=_weighted([c.entropy for c in cells], sizes),
            train_seconds=statistics.fmean(c.train_seconds for c in cells),
            units=tuple(unit_rows),
        ))
    return out
