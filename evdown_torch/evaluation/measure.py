"""The measures of every cell of a study, from what its stages produced."""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

import torch

from evdown_torch.evaluation import classifier
from evdown_torch.evaluation.cells import BASELINE
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.data import StudyData
from evdown_torch.evaluation.plan import Planned, delay_of
from evdown_torch.evaluation.results import CellResult
from evdown_torch.evaluation.statistics import hierarchical_means, interval_of

__all__ = ["Filled", "measure_cells"]


@dataclass
class Filled:
    """What the stages of one study (or one fold of it) produced, cell by cell."""

    planned: list[Planned]
    stats: dict
    predictions: dict
    found: dict
    rates: dict
    generated: int


def measure_cells(config: EvaluationConfig, source: StudyData, filled: Filled, speeds: dict
                  ) -> list[CellResult]:
    """One :class:`CellResult` per planned cell of ``filled``, timed as ``speeds`` says."""
    sensor = source.sensor_size
    st = config.statistics
    results = []
    for p in filled.planned:
        cell = p.cell
        test = filled.stats[cell]["test"]
        runs = filled.predictions[cell]
        seeds = tuple(sorted(runs))
        correct = tuple(tuple(runs[s]["correct"]) for s in seeds)
        w, h, _ = cell.output_size(sensor)
        model = classifier.model_for(classifier.trained_with(config, cell), (w, h),
                                     source.num_classes)
        n = len(test["events_out"])
        out_total, in_total = sum(test["events_out"]), sum(test["events_in"])
        fan_out = (model.stem_channels if model.stem is not None else model.channels[0] * 9)
        camera = None
        if source.has_ground_truth:
            # over the test recordings compared with the camera (the first ones)
            seen = sum(test["events_out"][:len(test["camera_events"])])
            camera = 1.0 if cell.method == BASELINE else (
                seen / sum(test["camera_events"]) if sum(test["camera_events"]) else math.inf)
        speed = speeds[cell]
        results.append(CellResult(
            cell=cell, role=p.role, output_size=(w, h), seeds=seeds, correct=correct,
            predicted=tuple(tuple(runs[s]["predicted"]) for s in seeds),
            labels=tuple(runs[seeds[0]]["labels"]),
            learning_rate=filled.rates[cell.factor][0],
            accuracy=statistics.fmean(statistics.fmean(r) for r in correct),
            interval=interval_of(hierarchical_means([torch.tensor(correct)],
                                                    resamples=st.resamples,
                                                    seed=st.seed)[:, 0],
                                 confidence=st.confidence),
            events_per_recording=out_total / n,
            events_per_second=out_total / max(sum(test["duration"]) * 1e-6, 1e-9),
            reduction=in_total / out_total if out_total else math.inf,
            rate_vs_camera=camera,
            consistency=statistics.fmean(test["consistency"]) if test["consistency"] else None,
            density=statistics.fmean(test["density"]),
            entropy=statistics.fmean(test["entropy"]),
            throughput=None if speed is None else speed[0],
            cpu_us_per_recording=None if speed is None else speed[1],
            delay=delay_of(cell),
            macs_per_recording=model.macs_per_step(h, w) * config.data.time_bins,
            synops_per_recording=out_total / n * fan_out,
            calibration=filled.found.get(cell),
            train_seconds=statistics.fmean(r["seconds"] for r in runs.values()),
        ))
    return results
