"""The cells of a study and the jobs that fill them, each runnable in a worker process.

A :class:`Cell` is one row of the table: a method (a registry name, the thinning
:data:`CONTROL` or the :data:`BASELINE`), a factor, an event budget and the settings that
were calibrated to it. The jobs below are plain functions of picklable arguments; each reads
its inputs from the cache and stores what it made there, so that a second run reads it back.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, TensorDataset

from evdown_torch.checks import output_size
from evdown_torch.config import EvaluationConfig
from evdown_torch.evaluation.cache import Cache, code_fingerprint
from evdown_torch.evaluation.data import Source, window
from evdown_torch.events import DVS_DTYPE, Events, to_events
from evdown_torch.frames import to_frames
from evdown_torch.metrics import event_metrics, optical_consistency
from evdown_torch.models.classifier import SpikingClassifier, stem_stride_for
from evdown_torch.training import predict_classifier, train_classifier
from evdown_torch.transforms._base import Downscaler
from evdown_torch.transforms.calibrate import BudgetTarget, calibration
from evdown_torch.transforms.registry import make_method
from evdown_torch.transforms.thinning import ThinnedDownsample

__all__ = ["BASELINE", "CONTROL", "TONIC", "Cell", "TonicPeer", "frames_of", "model_for"]

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
    """

    method: str
    factor: tuple[int, int]
    budget: float | None = None
    settings: tuple[tuple[str, Any], ...] = ()

    def transform(self, sensor_size: tuple[int, int, int], draw: int = 0) -> Downscaler | None:
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
        return output_size(sensor_size, self.factor)

    def key(self) -> dict[str, Any]:
        return {"method": self.method, "factor": list(self.factor), "budget": self.budget,
                "settings": [[k, v] for k, v in self.settings]}

    @property
    def label(self) -> str:
        if self.method == BASELINE:
            return BASELINE
        f = self.factor
        text = f"{self.method} x{f[0] if f[0] == f[1] else f'{f[0]}x{f[1]}'}"
        delay = dict(self.settings).get("max_delay")
        if delay is not None:
            text += f" (max_delay {delay:g})"
        return text if self.budget is None else f"{text} @ {self.budget:g}"

    def with_settings(self, **values: Any) -> Cell:
        merged = {**dict(self.settings), **values}
        return Cell(self.method, self.factor, self.budget, tuple(sorted(merged.items())))


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


def generate_job(source: Source, split: str, indices: list[int],
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


def calibrate_job(source: Source, cell: Cell, target_count: float, samples: int
                  ) -> tuple[Cell, dict[str, Any]]:
    """Calibrate ``cell``'s budget setting on the first ``samples`` training recordings.

    The search starts from the cell's configured value of the setting (the method's default
    when not configured) and targets ``target_count`` output events over those recordings.

    Returns:
        The cell with its calibrated settings, and what the search found.
    """
    sensor = source.sensor_size
    transform = cell.transform(sensor)
    setting = type(transform).budget_setting
    key = {"data": source.key("train"), "samples": samples, "cell": cell.key(),
           "target": target_count, "code": code_fingerprint(*_TRANSFORM_CODE)}
    cache = source.cache
    path = cache.path("calibrations", key, ".json")
    if not path.is_file():
        recordings = [source.recording("train", i)[0] for i in range(samples)]
        found = calibration(transform, recordings, BudgetTarget.count(target_count))
        cache.save_json(path, {"value": found.value, "count": found.count,
                               "target": found.target, "evaluations": found.evaluations})
    result = Cache.load_json(path)
    return cell.with_settings(**{setting: result["value"]}), result


def _frames_key(source: Source, cell: Cell, split: str, indices: list[int],
                config: EvaluationConfig, draw: int = 0) -> dict[str, Any]:
    return {"data": source.key(split), "indices": [indices[0], indices[-1] + 1],
            "cell": cell.key(), "draw": draw if cell.random else None,
            "bins": config.data.time_bins,
            "mean_time": config.data.mean_time,
            "consistency_bin_us": config.measures.consistency_bin_us,
            "code": code_fingerprint(*_TRANSFORM_CODE, "frames.py", "metrics.py",
                                     "evaluation/cells.py")}


#: Methods whose recordings go through ``transform.batch`` in groups of :data:`BATCH`: their
#: batched kernel is cheaper than one call per recording even for long recordings (LIFPooling's
#: rounds, one per time step of the busiest region, are shared by the whole batch: 0.5 to 0.9
#: of the per-recording time on the quick study's 6 s recordings). The other methods' cost
#: follows the events, and stacking long recordings only adds work.
BATCHED = frozenset({"lif"})
BATCH = 8


def downscale_job(source: Source, units: list[tuple[Cell, int]], split: str,
                  indices: list[int], config: EvaluationConfig) -> list[dict[str, list[float]]]:
    """Downscale recordings ``indices`` of ``split`` into each unit's frames, and measure them.

    A unit is a cell and a draw (the thinning control's seed; 0 for the other cells). The
    recordings (and, on the test split, the camera's renders) are read once for all the
    units. Per unit, the frames (``[n, T, 2, H, W]`` int16 event counts over each source
    recording's window, and with ``data.mean_time`` the ``[n, T, 2, H, W]`` int8 mean times,
    scaled by :data:`TIME_SCALE`) and labels are cached; the per-recording measures of draw 0
    are returned (and cached with them): ``events_in``, ``events_out``, ``seconds`` (of the
    transform), ``duration`` (us), ``density``, ``entropy`` and, with ground truth on the test
    split, ``camera_events`` and ``consistency``. Other draws return empty measures.

    Returns:
        The measures of each unit, in the order of ``units``.
    """
    cache = source.cache
    paths = [cache.path("frames", _frames_key(source, c, split, indices, config, d), ".pt")
             for c, d in units]
    todo = [j for j, path in enumerate(paths) if not path.is_file()]
    if todo:
        sensor = source.sensor_size
        inputs = []
        for i in indices:
            raw, label = source.recording(split, i)
            inputs.append((to_events(raw, sensor)[0], label, window(raw)))
        cameras: dict[tuple[int, int], list[Any]] = {}
        groups: dict[Cell, list[int]] = {}
        for j in todo:
            groups.setdefault(units[j][0], []).append(j)
        for cell, members in groups.items():
            camera = None
            if split == "test" and source.has_ground_truth and cell.method != BASELINE:
                if cell.factor not in cameras:
                    cameras[cell.factor] = [source.ground_truth(split, i, cell.factor)
                                            for i in indices]
                camera = cameras[cell.factor]
            _downscale_cell(cache, [paths[j] for j in members], cell,
                            [units[j][1] for j in members], inputs, camera, sensor, config)
    return [Cache.load_json(path.with_suffix(".json")) for path in paths]


def _downscale_cell(cache: Cache, paths: list[Any], cell: Cell, draws: list[int],
                    inputs: list[tuple[Any, int, Any]], cameras: list[Any] | None,
                    sensor: tuple[int, int, int], config: EvaluationConfig) -> None:
    """:func:`downscale_job` for the ``draws`` of one cell: ``inputs`` are ``(events, label,
    window)``. Draw 0 is measured (with ``cameras``, optical consistency too)."""
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
            per_stream = [transform.draws(events, draws) for events in part]
            made = [[out[d] for out in per_stream] for d in range(len(draws))]
        elif group > 1:
            made = [transform.batch(part)]
        else:
            made = [[transform.kernel(part[0])]]
        seconds += [(time.perf_counter() - start) / len(part) / len(draws)] * len(part)
        for d, out in enumerate(made):
            outputs[d] += out
    for path, draw, out in zip(paths, draws, outputs):
        _store_frames(cache, path, cell, inputs, out, seconds,
                      cameras if draw == 0 else None, draw == 0, sensor, config)


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
        if cameras is not None:
            stats["camera_events"].append(len(cameras[k]))
            stats["consistency"].append(optical_consistency(
                out, cameras[k], out_sensor, bin_width=config.measures.consistency_bin_us,
                t_start=t0, t_end=t1))
    stored = {"frames": torch.stack(frames), "labels": torch.tensor(labels, dtype=torch.int64)}
    if times:
        stored["times"] = torch.stack(times)
    cache.save_tensors(path, stored)
    cache.save_json(path.with_suffix(".json"), stats)


def frames_of(source: Source, cell: Cell, split: str, chunks: list[list[int]],
              config: EvaluationConfig, draw: int = 0) -> tuple[Tensor, Tensor]:
    """A cell's classifier input and labels of ``split`` (after :func:`downscale_job`).

    Returns:
        ``[n, T, C, H, W]`` float16 input (``C`` = ``data.frame_channels``: the counts
        encoded by ``training.encoding``, then the mean times in ``[-1, 1]``) and ``[n]``
        labels.
    """
    parts = [Cache.load_tensors(source.cache.path(
        "frames", _frames_key(source, cell, split, c, config, draw), ".pt")) for c in chunks]
    x = _encode(torch.cat([p["frames"] for p in parts]), config.training.encoding)
    if config.data.mean_time:
        times = torch.cat([p["times"] for p in parts]).to(torch.float16) / TIME_SCALE
        x = torch.cat([x.to(torch.float16), times], dim=2)
    return x, torch.cat([p["labels"] for p in parts])


def model_for(config: EvaluationConfig, size: tuple[int, int], num_classes: int
              ) -> SpikingClassifier:
    """The classifier of a cell whose frames are ``size = (W, H)``."""
    m = config.model
    return SpikingClassifier(
        num_classes, in_channels=config.data.frame_channels, channels=m.channels,
        pool_size=m.pool_size, beta=m.beta, threshold=m.threshold,
        stem_stride=stem_stride_for(size, m.grid) if m.grid else 1,
        stem_channels=m.stem_channels,
    )


def _encode(counts: Tensor, encoding: str) -> Tensor:
    """Classifier input from event counts (float16 for ``log``, ``binary``; else float32)."""
    counts = counts.to(torch.float32)
    if encoding == "log":
        return torch.log1p(counts).to(torch.float16)
    if encoding == "binary":
        return (counts > 0).to(torch.float16)
    return counts


def count_scale(x: Tensor) -> float:
    """The root mean square of the count channels (0 and 1) of ``[n, T, C, H, W]`` input.

    Dividing a cell's input by the scale of its training frames gives every cell input of
    the same energy, whatever its event rate: a dense cell (every event of Downsample) is not
    fed currents many times those of a sparse one (the same events thinned), which would
    saturate the first spiking layer and make a superset of events score below its subset.
    An input without events has scale 1.

    Example:
        >>> import torch
        >>> x = torch.zeros(2, 3, 4, 5, 5)
        >>> x[:, :, :2] = 2.0
        >>> count_scale(x), count_scale(torch.zeros(1, 1, 2, 1, 1))
        (2.0, 1.0)
    """
    counts = x[:, :, :2].to(torch.float64)
    rms = float(counts.square().mean().sqrt()) if counts.numel() else 0.0
    return rms if rms > 0 else 1.0


def draw_training_set(labels: Tensor, per_seed: int, seed: int,
                      exclude: int = 0) -> Tensor:
    """The training recordings of one seed: a class-stratified draw without replacement.

    Each seed trains on its own draw from the training pool (its rows ``exclude:`` of
    ``labels``; the first ``exclude`` are the validation recordings), so that seeds vary
    the training set as a replication would. Each class gives ``per_seed // classes``
    recordings, the remainder going one each to the classes in order; a class with fewer
    gives all it has.

    Args:
        labels: ``[n]`` int64 labels of the pool.
        per_seed: recordings wanted (0: the whole pool past ``exclude``).
        seed: the draw's seed.
        exclude: leading rows never drawn.

    Returns:
        Sorted ``[m]`` int64 row indices into ``labels``.

    Example:
        >>> import torch
        >>> labels = torch.arange(12) % 3
        >>> rows = draw_training_set(labels, 6, seed=0)
        >>> len(rows), torch.bincount(labels[rows]).tolist()
        (6, [2, 2, 2])
        >>> bool((draw_training_set(labels, 6, seed=1, exclude=3) >= 3).all())
        True
    """
    rows = torch.arange(exclude, len(labels))
    if per_seed == 0 or per_seed >= len(rows):
        return rows
    pool = labels[exclude:]
    classes = torch.unique(pool)
    g = torch.Generator().manual_seed(int(seed))
    base, extra = divmod(per_seed, len(classes))
    chosen = []
    for k, c in enumerate(classes.tolist()):
        members = rows[pool == c]
        take = min(len(members), base + (k < extra))
        chosen.append(members[torch.randperm(len(members), generator=g)[:take]])
    return torch.sort(torch.cat(chosen)).values


def train_job(source: Source, cell: Cell, chunks: dict[str, list[list[int]]],
              config: EvaluationConfig, seed: int, device: str, learning_rate: float,
              validation: bool = False) -> dict[str, Any]:
    """Train a fresh classifier on ``cell``'s frames under ``seed``; test it.

    Seed ``s`` fixes the initial weights, the order of the batches, the draw of training
    recordings from the pool (:func:`draw_training_set`) and, for the thinning control, the
    thinning draw. With ``validation`` the classifier trains on a draw from the pool less
    its first ``data.validation_samples`` recordings and is tested on those (to choose the
    learning rate); otherwise it trains on a draw from the whole pool and is tested on the
    test split. With ``training.normalise`` the count channels are divided by their
    :func:`count_scale` over the seed's training frames (train and test alike).

    Returns:
        ``{"correct": [bool per test recording], "predicted": [int per test recording],
        "labels": [int per test recording], "seconds": training time}`` (cached).
    """
    training = config.training
    draw = seed if cell.random else 0
    splits = ("train",) if validation else ("train", "test")
    frames_keys = {s: [_frames_key(source, cell, s, c, config, draw) for c in chunks[s]]
                   for s in splits}
    held_out = config.data.validation_samples if validation else 0
    key = {"frames": frames_keys, "model": config.model.__dict__, "epochs": training.epochs,
           "batch_size": training.batch_size, "learning_rate": learning_rate,
           "encoding": training.encoding, "normalise": training.normalise,
           "per_seed": config.data.train_per_seed, "validation": held_out, "seed": seed,
           "device": torch.device(device).type, "code": code_fingerprint("models", "training.py",
                                                                          "evaluation/cells.py")}
    cache = source.cache
    path = cache.path("predictions", key, ".json")
    if path.is_file():
        return Cache.load_json(path)
    pool_x, pool_y = frames_of(source, cell, "train", chunks["train"], config, draw)
    rows = draw_training_set(pool_y, config.data.train_per_seed, seed, exclude=held_out)
    train_x, train_y = pool_x[rows], pool_y[rows]
    if validation:
        test_x, test_y = pool_x[:held_out], pool_y[:held_out]
    else:
        test_x, test_y = frames_of(source, cell, "test", chunks["test"], config, draw)
    del pool_x
    if training.normalise:
        scale = count_scale(train_x)
        for x in (train_x, test_x):
            x[:, :, :2] /= scale
    size = (train_x.shape[-1], train_x.shape[-2])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = model_for(config, size, source.num_classes)
    model.to(device)
    order = torch.Generator().manual_seed(seed)
    start = time.perf_counter()
    train_classifier(model, DataLoader(TensorDataset(train_x, train_y),
                                       batch_size=training.batch_size, shuffle=True,
                                       generator=order),
                     epochs=training.epochs, learning_rate=learning_rate)
    seconds = time.perf_counter() - start
    predicted, labels = predict_classifier(
        model, DataLoader(TensorDataset(test_x, test_y), batch_size=training.batch_size))
    result = {"correct": (predicted == labels).tolist(), "predicted": predicted.tolist(),
              "labels": labels.tolist(), "seconds": seconds}
    cache.save_json(path, result)
    return result


def throughput(source: Source, cell: Cell, recordings: int
               ) -> tuple[float, float] | None:
    """Speed of ``cell``'s transform on the first test recordings, timed in this process
    (call it on one idle thread).

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
