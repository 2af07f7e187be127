"""The study's comparisons, cell against reference, once every cell is measured.

On the dataset's own train/test split (no ``data.folds``) a comparison resamples each cell's
``[seeds, recordings]`` correctness (:func:`~evdown_torch.evaluation.analysis.compare`); under
cross-validation it takes each cell's accuracy per ``(repeat, fold)``, its seeds averaged, and
applies the corrected resampled t-test to the paired differences
(:func:`~evdown_torch.evaluation.analysis.compare_splits`). Either way every cell is compared
on the same test recordings as its reference; where both trained on the same seeds (every
cell under cross-validation) the seeds are paired too.
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import torch
from torch import Tensor

from evdown_torch.evaluation.analysis import (
    Comparison,
    compare,
    compare_splits,
    noninferiority,
    sanity_check,
)
from evdown_torch.evaluation.cells import CONTROL
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.plan import EXPLORATORY, PRIMARY, SANITY
from evdown_torch.evaluation.results import CellResult

__all__ = ["compare_cells", "control_of", "split_accuracies"]


def split_accuracies(cell: CellResult, config: EvaluationConfig) -> Tensor:
    """``[J]`` accuracy of ``cell`` per ``(repeat, fold)``, its seeds averaged.

    In ``config.data.fold_units`` order, from ``cell.units``.

    Raises:
        ValueError: if the cell lacks a fold of the configuration.
    """
    per_split: dict[tuple[int, int], list[float]] = {}
    for repeat, fold, _, accuracy, _ in cell.units:
        per_split.setdefault((repeat, fold), []).append(accuracy)
    missing = [u for u in config.data.fold_units if u not in per_split]
    if missing:
        raise ValueError(f"{cell.cell.label} lacks the (repeat, fold) unit(s) {missing}")
    return torch.tensor([statistics.fmean(per_split[u]) for u in config.data.fold_units],
                        dtype=torch.float64)


def _standing(cell: CellResult) -> tuple:
    """Where a cell stands: its factor, budget and classifier."""
    return cell.factor, cell.budget, cell.cell.classifier


def control_of(cells: Sequence[CellResult], cell: CellResult) -> CellResult | None:
    """The control ``cell`` is compared with: the first of ``cells`` that fits.

    The control matched to ``cell``'s method at its factor
    (:attr:`~evdown_torch.evaluation.cells.Cell.matches`), else a control at its factor,
    budget and classifier (a control is its own); ``None`` if there is none.
    """
    for other in cells:
        if other.method == CONTROL and other.factor == cell.factor and (
                other.cell.matches == cell.method if other.cell.matches is not None
                else _standing(other) == _standing(cell)):
            return other
    return None


def compare_cells(results: list[CellResult], config: EvaluationConfig) -> tuple[
        list[CellResult], dict[tuple[int, int], Comparison], dict[tuple[int, int], Comparison]]:
    """The study's comparisons.

    The primary family: each primary method against the control and, with
    ``methods.primary_peer``, against that peer, at each primary factor and its budget
    (one-sided, Holm within the whole family); the sanity check per factor; every other
    budgeted cell against the control at its factor and budget, and a peer run at its own rate
    (Tonic's ``EventDownsampling``) against the control matched to its output count
    (exploratory: interval and TOST only); and ``methods.noninferiority`` per primary factor.

    Returns:
        ``(results, sanity, noninferiority)``: the cells with their ``comparison`` (and
        ``peer_comparison``) filled, the sanity check per factor, the non-inferiority test per
        primary factor.
    """
    st, m = config.statistics, config.methods
    folds = config.data.folds
    options: dict[str, Any] = dict(confidence=st.confidence, alpha=st.alpha,
                                   margin=m.equivalence_margin)

    def data(r: CellResult) -> Tensor:
        if folds:
            return split_accuracies(r, config)
        return torch.tensor(r.correct, dtype=torch.bool)

    def run(cells: list[tuple[CellResult, CellResult]], primary: bool) -> list[Comparison]:
        pairs = [(data(a), data(b)) for a, b in cells]
        if folds:
            return compare_splits(pairs, primary=primary, test_over_train=1 / (folds - 1),
                                  **options)
        return compare(pairs, primary=primary, resamples=st.resamples, seed=st.seed,
                       paired=[a.seeds == b.seeds for a, b in cells], **options)

    def first(method: str) -> dict[tuple, CellResult]:
        found: dict[tuple, CellResult] = {}
        for r in results:
            if r.method == method and r.cell.matches is None and _standing(r) not in found:
                found[_standing(r)] = r
        return found

    controls = first(CONTROL)
    peers = first(m.primary_peer) if m.primary_peer else {}
    out = list(results)
    # (cell's index, its reference, which comparison it fills)
    family = [(i, references[_standing(r)], which) for i, r in enumerate(results)
              if r.role == PRIMARY
              for references, which in ((controls, "comparison"), (peers, "peer_comparison"))
              if _standing(r) in references]
    others = [(i, control, "comparison") for i, r in enumerate(results)
              if r.role == EXPLORATORY and r.method != CONTROL
              and (control := control_of(results, r)) is not None]
    for group, primary in ((family, True), (others, False)):
        found = run([(results[i], reference) for i, reference, _ in group], primary)
        for (i, _, which), k in zip(group, found):
            out[i] = (replace(out[i], comparison=k) if which == "comparison"
                      else replace(out[i], peer_comparison=k))
    sanity = {}
    for i, r in enumerate(results):
        control = controls.get((r.factor, m.budget_at(r.factor), ()))
        if r.role == SANITY and control is not None:
            if folds:
                (sanity[r.factor],) = run([(control, r)], True)
            else:
                sanity[r.factor] = sanity_check(data(r), data(control), resamples=st.resamples,
                                                seed=st.seed, paired=r.seeds == control.seeds,
                                                **options)
            out[i] = replace(out[i], comparison=sanity[r.factor])
    verdicts: dict[tuple[int, int], Comparison] = {}
    if m.noninferiority:
        tested, reference = (first(name) for name in m.noninferiority)
        keys = [key for key in tested if key in reference and key[1] == m.budget_at(key[0])
                and not key[2]]  # the study's own classifier
        found = run([(tested[key], reference[key]) for key in keys], False)
        checked = noninferiority(found, margin=m.noninferiority_margin, alpha=st.alpha,
                                 splits=len(config.data.fold_units) if folds else None)
        verdicts = {key[0]: k for key, k in zip(keys, checked)}
    return out, sanity, verdicts
