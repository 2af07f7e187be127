"""The cells of a study and the jobs that fill them, each runnable in a worker process.

A :class:`Cell` is one row of the table: a method (a registry name, the thinning
:data:`CONTROL` or the :data:`BASELINE`), a factor, an event budget and the settings that
were calibrated to it. The jobs below are plain functions of picklable arguments; each reads
its inputs from the cache and stores what it made there, so that a second run reads it back.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np
import torch

from evdown_torch.checks import output_size
from evdown_torch.evaluation.cache import Cache, code_fingerprint
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.data import StudyData, window
from evdown_torch.evaluation.metrics import event_metrics, optical_consistency
from evdown_torch.events import DVS_DTYPE, Events, to_events
from evdown_torch.frames import to_frames
from evdown_torch.transforms import Downscaler
from evdown_torch.transforms.calibrate import BudgetTarget, calibration
from evdown_torch.transforms.registry import make_method
from evdown_torch.transforms.thinning import ThinnedDownsample

__all__ = ["BASELINE", "CONTROL", "TONIC", "Cell", "TonicPeer", "frames_key"]

#: The method name of the full-resolution row.
BASELINE = "full resolution"
#: The method name of the thinning control (Downsample thinned at random to the budget).
CONTROL = "control"
#: The method name of the peer: Tonic's ``EventDownsampling`` (integrator, Ghosh et al. 2023).
TONIC = "tonic integrator"
#: Its time step (ms) and noise threshold, as in ``evdown bench``.
TONIC_DT_MS, TONIC_NOISE_THRESHOLD = 1.0, 1

_TRANSFORM_CODE = ("transforms", "events.py", "checks.py")
#: Mean times in ``[-1, 1]`` are cached as int8 multiples of ``1 / TIME_SCALE``.
TIME_SCALE = 127


@dataclass(frozen=True)
class Cell:
    """One row of the study.

    Attributes:
        method: a registry name, :data:`CONTROL` or :data:`BASELINE`.
        factor: ``(fx, fy)``; ``(1, 1)`` for the baseline.
        budget: the event budget as a multiple of the reference (the low-resolution camera's
            count, or the input's), or ``None`` for a method run at its own settings.
        settings: the transform's settings, the calibrated budget setting included, as
            sorted ``(name, value)`` pairs.
        matches: for a control without a budget, the method (a peer run at its own rate,
            :data:`TONIC`) whose output count on the calibration recordings its thinning is
            calibrated to; ``None`` otherwise.
        classifier: settings that replace the study's classifier for this row (``channels``,
            ``epochs``: :class:`~evdown_torch.evaluation.config_tables.RobustnessConfig`) as
            ``(name, value)`` pairs; the cell's frames and calibration are those of the cell
            without them (:meth:`key` leaves them out).
    """

    method: str
    factor: tuple[int, int]
    budget: float | None = None
    settings: tuple[tuple[str, Any], ...] = ()
    matches: str | None = None
    classifier: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        if self.matches is not None and (self.method != CONTROL or self.budget is not None):
            raise ValueError(f"only a control without a budget matches another method's "
                             f"output, got {self.method!r} at budget {self.budget!r}")

    def transform(self, sensor_size: tuple[int, int, int], draw: int = 0
                  ) -> Downscaler | TonicPeer | None:
        """The downscaler of this cell (``None`` for the baseline).

        ``draw`` seeds the control's random thinning (each training seed has its own draw);
        the other methods are deterministic and ignore it.
        """
        if self.method == BASELINE:
            return None
        if self.method == CONTROL:
            return ThinnedDownsample(sensor_size, self.factor, **dict(self.settings), seed=draw)
        if self.method == TONIC:
            return TonicPeer(sensor_size, self.factor)
        return make_method(self.method, sensor_size, self.factor, **dict(self.settings))

    @property
    def random(self) -> bool:
        """Whether the cell's output depends on the draw (the thinning control)."""
        return self.method == CONTROL

    def output_size(self, sensor_size: tuple[int, int, int]) -> tuple[int, int, int]:
        """The sensor the cell's output lives on, for an input of ``sensor_size``."""
        return output_size(sensor_size, self.factor)

    def key(self) -> dict[str, Any]:
        """The cell's settings as a cache key of its frames and calibration (JSON-ready).

        Without :attr:`classifier`: a row trained with another classifier shares its frames.
        """
        key = {"method": self.method, "factor": list(self.factor), "budget": self.budget,
               "settings": [[k, v] for k, v in self.settings]}
        return key if self.matches is None else {**key, "matches": self.matches}

    @property
    def label(self) -> str:
        """The cell's name in tables and plots."""
        if self.method == BASELINE:
            return BASELINE
        f = self.factor
        text = f"{self.name} x{f[0] if f[0] == f[1] else f'{f[0]}x{f[1]}'}"
        return text if self.budget is None else f"{text} @ {self.budget:g}"

    @property
    def name(self) -> str:
        """The method, with its delay where one is set (``max_delay`` read as microseconds).

        Example:
            >>> Cell(CONTROL, (4, 4), matches=TONIC).name
            'control (matched to tonic integrator)'
            >>> Cell("event_count", (4, 4), 1.0, classifier=(("channels", (32, 64)),)).name
            'event_count (classifier channels 32-64)'
        """
        if self.matches is not None:
            return f"{self.method} (matched to {self.matches})"
        delay = dict(self.settings).get("max_delay")
        name = self.method if delay is None else f"{self.method} (max_delay {delay / 1000:g} ms)"
        if self.classifier:
            name += " (classifier " + ", ".join(
                f"{k} {'-'.join(map(str, v)) if isinstance(v, tuple) else v}"
                for k, v in self.classifier) + ")"
        return name

    def with_settings(self, **values: Any) -> Cell:
        """The same cell with ``values`` added to (or replacing) its settings."""
        merged = {**dict(self.settings), **values}
        return replace(self, settings=tuple(sorted(merged.items())))


class TonicPeer:
    """Tonic's ``EventDownsampling`` integrator as a study row: what a user would pick instead.

    It integrates each output pixel's input on dense frames of ``TONIC_DT_MS`` and fires where
    the integral passes ``TONIC_NOISE_THRESHOLD``; its output is its own (no budget setting is
    searched: its threshold is an integer event count, too coarse to meet a budget). Needs
    tonic; expects microsecond timestamps.
    """

    def __init__(self, sensor_size: tuple[int, int, int], factor: tuple[int, int]) -> None:
        try:
            import tonic
        except ModuleNotFoundError:
            raise RuntimeError("methods.tonic_peer needs tonic: pip install tonic (or "
                               "evdown_torch[tonic])") from None

        self.out_sensor = output_size(sensor_size, factor)
        self.peer = tonic.transforms.EventDownsampling(
            sensor_size=tuple(sensor_size), target_size=self.out_sensor[:2], dt=TONIC_DT_MS,
            downsampling_method="integrator", noise_threshold=TONIC_NOISE_THRESHOLD)

    def kernel(self, events: Events) -> Events:
        """Downscale ``events`` through Tonic (a structured array there and back)."""
        data = np.zeros(events.num_events, DVS_DTYPE)
        for name, column in zip("xytp", events):
            data[name] = column.cpu().numpy()
        out = self.peer(data)
        if len(out) == 0:
            return Events.empty(device=events.device)
        return to_events(out, self.out_sensor)[0]


# ----------------------------------------------------------------------------- jobs


def generate_job(source: StudyData, split: str, indices: list[int],
                 factor: tuple[int, int] = (1, 1)) -> tuple[int, list[int]]:
    """Cache recordings ``indices`` of ``split`` (or their renders at ``factor``).

    Returns:
        ``(generated, counts)``: how many were not cached yet, and each one's event count.
    """
    generated, counts = 0, []
    for i in indices:
        if factor == (1, 1):
            generated += source.ensure(split, i)
            counts.append(len(source.recording(split, i)[0]))
        else:
            generated += source.ensure(split, i, factor)
            counts.append(len(source.ground_truth(split, i, factor)))
    return generated, counts


def calibrate_job(source: StudyData, cell: Cell, target_count: float, samples: int,
                  split: str = "train") -> tuple[Cell, dict[str, Any]]:
    """Calibrate ``cell``'s budget setting on the first ``samples`` recordings of ``split``.

    ``split`` is ``"train"`` or the held-out ``"calibration"`` split
    (:attr:`StudyData.calibration_split`).

    The search starts from the cell's configured value of the setting (the method's default
    when not configured) and targets ``target_count`` output events over those recordings.

    Returns:
        The cell with its calibrated settings, and what the search found.
    """
    sensor = source.sensor_size
    transform = cast(Downscaler, cell.transform(sensor))  # a budgeted cell's is a Downscaler
    setting = cast(str, type(transform).budget_setting)
    key = {"data": source.key(split), "samples": samples, "cell": cell.key(),
           "target": target_count, "code": code_fingerprint(*_TRANSFORM_CODE)}
    cache = source.cache
    path = cache.path("calibrations", key, ".json")
    if not path.is_file():
        recordings = [source.recording(split, i)[0] for i in range(samples)]
        found = calibration(transform, recordings, BudgetTarget.count(target_count))
        cache.save_json(path, {"value": found.value, "count": found.count,
                               "target": found.target, "evaluations": found.evaluations})
    result = Cache.load_json(path)
    return cell.with_settings(**{setting: result["value"]}), result


def output_count_job(source: StudyData, cell: Cell, samples: int, split: str = "train"
                     ) -> int:
    """How many events ``cell`` outputs over the first ``samples`` recordings of ``split``.

    The target a control matched to ``cell`` (:attr:`Cell.matches`) is calibrated to; cached.
    """
    key = {"data": source.key(split), "samples": samples, "cell": cell.key(),
           "code": code_fingerprint(*_TRANSFORM_CODE, "evaluation/cells.py")}
    path = source.cache.path("output_counts", key, ".json")
    if not path.is_file():
        transform = cast(TonicPeer | Downscaler, cell.transform(source.sensor_size))
        count = sum(transform.kernel(to_events(source.recording(split, i)[0],
                                               source.sensor_size)[0]).num_events
                    for i in range(samples))
        source.cache.save_json(path, {"count": count})
    return int(Cache.load_json(path)["count"])


def frames_key(source: StudyData, cell: Cell, split: str, indices: list[int],
                config: EvaluationConfig, draw: int = 0) -> dict[str, Any]:
    """The cache key of ``cell``'s frames of recordings ``indices`` of ``split`` (draw ``draw``)."""
    return {"data": source.key(split), "indices": [indices[0], indices[-1] + 1],
            "consistency_recordings": config.measures.consistency_recordings,
            "cell": cell.key(), "draw": draw if cell.random else None,
            "bins": config.data.time_bins,
            "mean_time": config.data.mean_time,
            "consistency_bin_us": config.measures.consistency_bin_us,
            "code": code_fingerprint(*_TRANSFORM_CODE, "frames.py", "evaluation/metrics.py",
                                     "evaluation/cells.py")}


#: Methods whose recordings go through ``transform.batch`` in groups of :data:`BATCH`: their
#: batched kernel is cheaper than one call per recording even for long recordings (LIFPooling's
#: rounds, one per time step of the busiest region, are shared by the whole batch: 0.5 to 0.9
#: of the per-recording time on the quick study's 6 s recordings). The other methods' cost
#: follows the events, and stacking long recordings only adds work.
BATCHED = frozenset({"lif"})
BATCH = 8


def measured_draws(units: list[tuple[Cell, int]]) -> dict[Cell, int]:
    """The draw whose measures stand for each cell of ``units``: its smallest.

    Example:
        >>> a, b = Cell("control", (2, 2), 1.0), Cell("downsample", (2, 2))
        >>> measured_draws([(a, 3), (b, 0), (a, 1)]) == {a: 1, b: 0}
        True
    """
    first: dict[Cell, int] = {}
    for cell, draw in units:
        first[cell] = min(draw, first.get(cell, draw))
    return first


def downscale_job(source: StudyData, units: list[tuple[Cell, int]], split: str,
                  indices: list[int], config: EvaluationConfig) -> list[dict[str, list[float]]]:
    """Downscale recordings ``indices`` of ``split`` into each unit's frames, and measure them.

    A unit is a cell and a draw (the thinning control's seed; 0 for the other cells). The
    recordings (and, on the test split, the camera's renders) are read once for all the
    units. Per unit, the frames (``[n, T, 2, H, W]`` int16 event counts over each source
    recording's window, and with ``data.mean_time`` the ``[n, T, 2, H, W]`` int8 mean times,
    scaled by :data:`TIME_SCALE`) and labels are cached; the per-recording measures of each
    cell's first draw (its smallest among ``units``) are returned (and cached with them):
    ``events_in``, ``events_out``, ``seconds`` (of the transform), ``duration`` (us),
    ``density``, ``entropy`` and, with ground truth on the test split, ``camera_events`` and
    ``consistency``. Other draws return the counts only.

    Returns:
        The measures of each unit, in the order of ``units``.
    """
    cache = source.cache
    paths = [cache.path("frames", frames_key(source, c, split, indices, config, d), ".pt")
             for c, d in units]
    # a unit is done once its measures are stored (after its frames): a run killed between
    # the two redoes it
    # (units that share frames, the same cell under another classifier, are made once)
    todo = [j for j, path in enumerate(paths)
            if not path.with_suffix(".json").is_file() and path not in paths[:j]]
    if todo:
        sensor = source.sensor_size
        inputs = []
        for i in indices:
            raw, label = source.recording(split, i)
            inputs.append((to_events(raw, sensor)[0], label, window(raw)))
        cameras: dict[tuple[int, int], list[Any]] = {}
        measured = measured_draws(units)
        groups: dict[Cell, list[int]] = {}
        for j in todo:
            groups.setdefault(units[j][0], []).append(j)
        for cell, members in groups.items():
            camera = None
            if split == "test" and source.has_ground_truth and cell.method != BASELINE:
                if cell.factor not in cameras:
                    limit = config.measures.consistency_recordings or len(indices) + indices[0]
                    cameras[cell.factor] = [source.ground_truth(split, i, cell.factor)
                                            for i in indices if i < limit]
                camera = cameras[cell.factor]
            _downscale_cell(cache, [paths[j] for j in members], cell,
                            [units[j][1] for j in members], measured[cell], inputs, camera,
                            sensor, config)
    return [Cache.load_json(path.with_suffix(".json")) for path in paths]


def _downscale_cell(cache: Cache, paths: list[Any], cell: Cell, draws: list[int],
                    measured: int, inputs: list[tuple[Any, int, Any]],
                    cameras: list[Any] | None, sensor: tuple[int, int, int],
                    config: EvaluationConfig) -> None:
    """:func:`downscale_job` for the ``draws`` of one cell.

    ``inputs`` are ``(events, label, window)``. Draw ``measured`` is measured (with
    ``cameras``, optical consistency too).
    """
    transform = cell.transform(sensor)
    streams = [events for events, _, _ in inputs]
    outputs: list[list[Any]] = [[] for _ in draws]  # per draw, per recording
    seconds: list[float] = []
    group = BATCH if cell.method in BATCHED else 1
    for lo in range(0, len(streams), group):
        part = streams[lo:lo + group]
        start = time.perf_counter()
        if transform is None:
            made = [part]
        elif cell.random:
            thinning = cast(ThinnedDownsample, transform)  # the random cell is the control
            per_stream = [thinning.draws(events, draws) for events in part]
            made = [[out[d] for out in per_stream] for d in range(len(draws))]
        elif group > 1:
            made = [cast(Downscaler, transform).batch(part)]  # BATCHED names methods only
        else:
            made = [[transform.kernel(part[0])]]
        seconds += [(time.perf_counter() - start) / len(part) / len(draws)] * len(part)
        for d, out in enumerate(made):
            outputs[d] += out
    for path, draw, out in zip(paths, draws, outputs):
        _store_frames(cache, path, cell, inputs, out, seconds,
                      cameras if draw == measured else None, draw == measured, sensor, config)


def _store_frames(cache: Cache, path: Any, cell: Cell, inputs: list[tuple[Any, int, Any]],
                  outputs: list[Any], seconds: list[float], cameras: list[Any] | None,
                  measure: bool, sensor: tuple[int, int, int], config: EvaluationConfig) -> None:
    """Bin one draw's ``outputs`` into frames, cache them, and measure them if ``measure``."""
    out_sensor = cell.output_size(sensor)
    stats: dict[str, list[float]] = {k: [] for k in (
        "events_in", "events_out", "seconds", "duration", "density", "entropy",
        "camera_events", "consistency")}
    stats["seconds"] = list(seconds)
    frames, times, labels = [], [], []
    for k, ((events, label, (t0, t1)), out) in enumerate(zip(inputs, outputs)):
        binned = to_frames(out, out_sensor, config.data.time_bins, t_start=t0, t_end=t1,
                           mean_time=config.data.mean_time)
        frames.append(binned[:, :2].clamp(max=torch.iinfo(torch.int16).max).to(torch.int16))
        if config.data.mean_time:
            times.append(torch.round(binned[:, 2:] * TIME_SCALE).to(torch.int8))
        labels.append(label)
        stats["events_in"].append(events.num_events)
        stats["events_out"].append(out.num_events)
        stats["duration"].append(t1 - t0)
        if not measure:
            continue
        metrics = event_metrics(out, out_sensor, duration=max(t1 - t0, 1))
        stats["density"].append(metrics.density)
        stats["entropy"].append(metrics.entropy)
        if cameras is not None and k < len(cameras):
            stats["camera_events"].append(len(cameras[k]))
            stats["consistency"].append(optical_consistency(
                out, cameras[k], out_sensor, bin_width=config.measures.consistency_bin_us,
                t_start=t0, t_end=t1))
    stored = {"frames": torch.stack(frames), "labels": torch.tensor(labels, dtype=torch.int64)}
    if times:
        stored["times"] = torch.stack(times)
    cache.save_tensors(path, stored)
    cache.save_json(path.with_suffix(".json"), stats)


def throughput(source: StudyData, cell: Cell, recordings: int
               ) -> tuple[float, float] | None:
    """Speed of ``cell``'s transform on the first test recordings, timed in this process.

    Call it on one idle thread.

    Returns:
        ``(input events per second, CPU microseconds per recording)``: the transform's kernel
        alone, after one warm-up call; ``None`` for the baseline or no recording.
    """
    transform = cell.transform(source.sensor_size)
    if transform is None or recordings == 0:
        return None
    streams = [to_events(source.recording("test", i)[0], source.sensor_size)[0]
               for i in range(min(recordings, source.size("test")))]
    transform.kernel(streams[0])  # warm up
    start, cpu = time.perf_counter(), time.process_time()
    for events in streams:
        transform.kernel(events)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    total = sum(e.num_events for e in streams)
    return (total / seconds if seconds > 0 else float("inf")), cpu / len(streams) * 1e6
