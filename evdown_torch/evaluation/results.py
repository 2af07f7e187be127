"""What a study returns: one :class:`CellResult` per cell, in an :class:`EvaluationResult`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from evdown_torch.evaluation.analysis import Comparison
from evdown_torch.evaluation.cells import Cell
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.plan import PRIMARY

__all__ = ["CellResult", "EvaluationResult", "RankRun"]


@dataclass(frozen=True)
class CellResult:
    """The measurements of one cell (test split unless said otherwise).

    Attributes:
        cell: the :class:`~evdown_torch.evaluation.cells.Cell`.
        role: ``"primary"``, ``"control"`` (the primary family's control), ``"sanity"``
            (Downsample at its own rate, against its thinning) or ``"exploratory"``.
        output_size: ``(W, H)`` of the frames.
        seeds: training seeds.
        correct: per seed, per test recording: classified correctly.
        predicted: per seed, per test recording: the class given.
        labels: per test recording: its class.
        learning_rate: the rate the classifier trained with (chosen per factor).
        accuracy: mean of ``correct``.
        interval: bootstrap confidence interval of the accuracy (seeds, then recordings).
        events_per_recording: mean output events per recording.
        events_per_second: output events per second of recording.
        reduction: input events / output events.
        rate_vs_camera: output events / the low-resolution camera's events; ``None`` without
            ground truth (1 for the baseline).
        consistency: mean optical consistency with the camera
            (:func:`~evdown_torch.evaluation.metrics.optical_consistency`); ``None`` without
            ground truth and for the baseline.
        density, entropy: the paper's measures, mean per recording.
        throughput: input events per second of the transform on one idle thread.
        cpu_us_per_recording: CPU microseconds of the transform per test recording.
        delay: the method's algorithmic delay, in words.
        macs_per_recording: the classifier's multiply-accumulates per recording (dense).
        synops_per_recording: synaptic operations of the classifier's first layer, output
            events times their fan-out.
        calibration: what the budget search found (``None`` without a budget).
        train_seconds: mean training time per seed.
        comparison: against the control at the same factor and budget (for the sanity
            row, the control against it); ``None`` where there is none.
        peer_comparison: a primary cell against ``methods.primary_peer`` at the same factor
            and budget (within the primary family); ``None`` otherwise.
        units: with ``data.folds``: ``(repeat, fold, seed, accuracy, learning_rate)`` of each
            training run (``correct`` then holds one row per ``(repeat, seed)`` over every
            pooled recording); ``()`` otherwise.
    """

    cell: Cell
    role: str
    output_size: tuple[int, int]
    seeds: tuple[int, ...]
    correct: tuple[tuple[bool, ...], ...]
    predicted: tuple[tuple[int, ...], ...]
    labels: tuple[int, ...]
    learning_rate: float
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
    cpu_us_per_recording: float | None
    delay: str
    macs_per_recording: int
    synops_per_recording: float
    calibration: dict[str, Any] | None
    train_seconds: float
    comparison: Comparison | None = None
    peer_comparison: Comparison | None = None
    units: tuple[tuple[int, int, int, float, float], ...] = ()

    @property
    def method(self) -> str:
        """The cell's method."""
        return self.cell.method

    @property
    def factor(self) -> tuple[int, int]:
        """The cell's factor ``(fx, fy)``."""
        return self.cell.factor

    @property
    def budget(self) -> float | None:
        """The cell's event budget, ``None`` for none."""
        return self.cell.budget

    @property
    def accuracies(self) -> tuple[float, ...]:
        """Test accuracy of each seed."""
        return tuple(sum(row) / len(row) for row in self.correct)

    def per_class(self, num_classes: int) -> tuple[float, ...]:
        """Accuracy on each class's test recordings, over every seed."""
        totals, right = [0] * num_classes, [0] * num_classes
        for row in self.correct:
            for label, ok in zip(self.labels, row):
                totals[label] += 1
                right[label] += ok
        return tuple(r / t if t else math.nan for r, t in zip(right, totals))


@dataclass(frozen=True)
class RankRun:
    """How one rank of a ``torchrun`` launch went.

    Attributes:
        rank: its rank.
        host: the machine it ran on.
        device: where it trained.
        jobs: the jobs it ran (made, or found in its cache).
        generated: recordings and renders it generated.
        wall_seconds: its wall time (rank 0: the whole run, measuring included).
        cpu_seconds: CPU seconds of the rank and its workers.
    """

    rank: int
    host: str
    device: str
    jobs: int
    generated: int
    wall_seconds: float
    cpu_seconds: float


@dataclass(frozen=True)
class EvaluationResult:
    """All cells of one run and how the run went.

    Attributes:
        config: the configuration.
        description: the data, in one line.
        cells: per factor: the primary cells, their control, the sanity row, then the
            exploratory cells (the baseline first).
        learning_rates: per factor, the rate chosen on the validation split, and the
            validation accuracy of every candidate.
        sanity: per factor, check (a): the control's accuracy minus Downsample's (a random
            subset against its superset), one-sided; the check passes where not significant.
        wall_seconds: the run's wall time.
        cpu_seconds: CPU seconds of this process and its workers (of every rank).
        workers: worker processes used (per rank).
        generated: recordings and renders generated (not read from the cache; by every rank).
        device: where the classifier trained (under ``torchrun``: the device type; each
            rank's device is in ``ranks``).
        ranks: under ``torchrun``, how each rank went; empty for one process.
        gathered_through: under ``torchrun``, how the results reached rank 0 (``"the shared
            cache folder"`` or ``"the process group"``); empty for one process.
        noninferiority: per primary factor, ``methods.noninferiority``'s tested method
            against its reference at the primary budget: ``significant`` where it is
            non-inferior within ``methods.noninferiority_margin`` (Holm over the factors).
    """

    config: EvaluationConfig
    description: str
    cells: tuple[CellResult, ...]
    learning_rates: dict[tuple[int, int], tuple[float, dict[float, float]]]
    sanity: dict[tuple[int, int], Comparison]
    wall_seconds: float
    cpu_seconds: float
    workers: int
    generated: int
    device: str
    ranks: tuple[RankRun, ...] = ()
    gathered_through: str = ""
    noninferiority: dict[tuple[int, int], Comparison] = field(default_factory=dict)

    def primary(self) -> list[CellResult]:
        """The primary family's method cells, in order."""
        return [c for c in self.cells if c.role == PRIMARY]
