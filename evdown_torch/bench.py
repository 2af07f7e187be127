"""Benchmarks: every downscaler against its peers, scaling curves and peak memory.

``evdown bench --out DIR [--short]`` (or :func:`run_benchmark` then :func:`write_report`)
measures, in one process and one run, every method of
:data:`~evdown_torch.transforms.registry.METHODS` and the peers a user would otherwise pick,
``tonic.transforms.Downsample`` and ``tonic.transforms.EventDownsampling`` (integrator and
differentiator; only when Tonic is installed), and writes ``report.md``, ``results.json`` and
PNG plots (when matplotlib is installed) to ``DIR``.

What is measured:

* **Time**: wall-clock time of one call of the transform on a Tonic structured array in
  memory (validation, conversion to tensors and back included, as a user calls it), with
  ``torch.set_num_threads(1)``; the median of at least ``repeats`` calls after one warm-up call
  (more calls for inputs that take only milliseconds), with the median CPU time of the same
  calls beside it. **Throughput** is input events divided by the median wall-clock time.
* **Peak memory**, per method and input, in a fresh process: one worker process imports
  everything (interpreter, NumPy, torch, evdown_torch, Tonic) and, for every measurement,
  forks a child that loads the input, builds the transform, warms it up on 1000 events and
  calls it once. *Added* is the child's peak resident set (``VmHWM``) during the call minus
  its resident set just before (the input loaded); *process* is the worker's resident set
  after imports plus the child's growth up to its peak, i.e. the peak of a fresh process
  that imports, loads the input and runs the method once. Without ``fork`` or ``/proc`` (not
  Linux), each measurement runs in its own fresh interpreter and *added* is the growth of the
  peak resident set (``ru_maxrss``) over the call.
* **Scaling curves** (factor 4) of throughput and added peak memory against the number of
  events at a fixed event rate, the sensor size at a fixed count and duration, and the
  recording duration at a fixed count (events arrive in bursts at a fixed rate; the pauses
  between bursts grow), so the curves show what the cost follows.

Inputs: synthetic DVS128-Gesture-like recordings (:func:`gesture_stream`, from
:mod:`evdown_torch.synthetic`) for the method table and the goals; streams of moving bar edges
(:func:`dvs_like_stream`, whose count, sensor and duration are set exactly) for the large
1280x720 input and the sweeps; the real N-MNIST sample in ``shared/data`` when present; and
any ``.npy`` structured arrays named.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import gc
import importlib
import importlib.util
import json
import math
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from evdown_torch.checks import (
    check_factor,
    check_positive_int,
    check_sensor_size,
    output_size,
)
from evdown_torch.events import load_npy_events
from evdown_torch.transforms.registry import METHODS, make_method, method_settings

__all__ = [
    "BENCH_SETTINGS",
    "DVS_DTYPE",
    "GOALS",
    "PEERS",
    "BenchResults",
    "Candidate",
    "Goal",
    "Measurement",
    "MemoryJob",
    "Timing",
    "candidate",
    "candidate_job",
    "candidates",
    "dvs_like_stream",
    "gesture_stream",
    "load_npy_events",
    "load_results",
    "measure_memory",
    "parse_spec",
    "prepare_candidate_call",
    "read_nmnist",
    "run_benchmark",
    "time_call",
    "with_pauses",
    "write_report",
]

#: Tonic's event dtype for DVS recordings (DVSGesture's).
DVS_DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("p", np.bool_), ("t", np.int64)])

#: Benchmark settings of the methods that need some, by method name (checked by the tests
#: against :func:`~evdown_torch.transforms.registry.method_settings`). Methods not named here
#: run with their defaults. Times are in the stream's unit (microseconds).
BENCH_SETTINGS: dict[str, dict[str, Any]] = {
    "lif": {"dt": 1000},
}

#: Peer settings: ``EventDownsampling`` time step in milliseconds, its noise threshold (with 0
#: every output pixel spikes at every step, so 1 is the smallest useful one) and its
#: differentiator time bins (Tonic's documented default).
PEER_DT_MS = 1.0
PEER_NOISE_THRESHOLD = 1
PEER_DIFFERENTIATOR_BINS = 2

#: Peers skip a measurement whose dense frames would need more than this (bytes).
PEER_MEMORY_BUDGET = 3_000_000_000

#: The paper's reference code, seconds per 100,000 events (issue 3).
PAPER_SECONDS_PER_100K = {"event_count": 0.8, "linear": 2.6, "cubic": 2.9}

_SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
NMNIST_FILE = _SHARED_DATA / "sample_nmnist.bin"

LARGE_RATE = 2_000_000.0  # events per second of the 1280x720 stream
EVENTS_SWEEP_RATE = 500_000.0  # events per second in the events sweep


def _log(message: str) -> None:
    print(f"[evdown bench] {message}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------- inputs


def dvs_like_stream(
    num_events: int,
    sensor_size: tuple[int, int, int] = (128, 128, 2),
    *,
    duration_us: int = 6_000_000,
    seed: int = 0,
    num_objects: int = 4,
    noise: float = 0.05,
    start_us: int = 0,
) -> np.ndarray:
    """A DVS-like random stream: edges of bars sweeping round like arms, plus background noise.

    Each object is a bar along a radius of a circle, turning at 1 to 4 turns per second; its
    leading edge emits one polarity and its trailing edge the other (bright or dark bars),
    with half a pixel of jitter. A share ``noise`` of the events is uniform background
    activity. Event times are uniform over ``[start_us, start_us + duration_us)``, sorted;
    several events can share a timestamp when the rate exceeds one per microsecond. The bars
    depend on ``seed`` only, so consecutive pieces (same seed, ``start_us`` advancing by
    ``duration_us``) continue one recording: long streams can be made piece by piece.

    Args:
        num_events: number of events ``N`` (>= 0).
        sensor_size: ``(W, H, P)``.
        duration_us: length of the recording in microseconds (> 0).
        seed: seed of the NumPy generator; the same seed gives the same stream.
        num_objects: number of moving bars (> 0).
        noise: share of background events, in ``[0, 1]``.
        start_us: time of the piece's start, microseconds (>= 0).

    Returns:
        ``(N,)`` structured array of :data:`DVS_DTYPE` (``t`` int64 microseconds), sorted by
        ``t``, inside the sensor.

    Example:
        >>> ev = dvs_like_stream(1000, (64, 48, 2), duration_us=10_000, seed=1)
        >>> len(ev), int(ev["x"].max()) < 64, bool((np.diff(ev["t"]) >= 0).all())
        (1000, True, True)
    """
    if not isinstance(num_events, (int, np.integer)) or isinstance(num_events, bool):
        raise TypeError(f"num_events must be a non-negative integer, got {num_events!r}")
    if num_events < 0:
        raise ValueError(f"num_events must be a non-negative integer, got {num_events!r}")
    w, h, _ = check_sensor_size(sensor_size)
    duration_us = check_positive_int("duration_us", duration_us)
    k = check_positive_int("num_objects", num_objects)
    if not 0.0 <= float(noise) <= 1.0:
        raise ValueError(f"noise must be a share in [0, 1], got {noise!r}")
    if not isinstance(start_us, (int, np.integer)) or isinstance(start_us, bool) or start_us < 0:
        raise ValueError(f"start_us must be a non-negative integer, got {start_us!r}")
    rng = np.random.default_rng(seed)
    n = int(num_events)
    size = min(w, h)
    centre = rng.uniform(0.4, 0.6, (k, 2)) * np.array([w, h])
    radius = rng.uniform(0.08, 0.2, k) * size
    length = rng.uniform(0.1, 0.25, k) * size
    width = rng.uniform(0.02, 0.05, k) * size + 1.0
    turn = rng.choice([-1.0, 1.0], k)
    omega = rng.uniform(1.0, 4.0, k) * turn * 2 * np.pi / 1e6  # radians per microsecond
    phase = rng.uniform(0, 2 * np.pi, k)
    bright = rng.random(k) < 0.5

    rng = np.random.default_rng([seed, int(start_us)])  # this piece's events
    t = np.sort(rng.integers(start_us, start_us + duration_us, n))
    obj = rng.integers(0, k, n)
    angle = phase[obj] + omega[obj] * t
    cos, sin = np.cos(angle), np.sin(angle)
    along = radius[obj] + (rng.random(n) - 0.5) * length[obj]
    leading = rng.random(n) < 0.5
    across = np.where(leading, 0.5, -0.5) * width[obj] + rng.normal(0.0, 0.5, n)
    px = centre[obj, 0] + along * cos - across * sin * turn[obj]
    py = centre[obj, 1] + along * sin + across * cos * turn[obj]
    p = leading == bright[obj]

    background = rng.random(n) < noise
    nb = int(background.sum())
    px[background] = rng.uniform(0, w, nb)
    py[background] = rng.uniform(0, h, nb)
    p[background] = rng.random(nb) < 0.5

    out = np.empty(n, dtype=DVS_DTYPE)
    out["x"] = np.clip(np.floor(px), 0, w - 1)
    out["y"] = np.clip(np.floor(py), 0, h - 1)
    out["p"] = p
    out["t"] = t
    return out


def gesture_stream(num_events: int, *, seed: int = 0,
                   sensor_size: tuple[int, int, int] = (128, 128, 2)) -> np.ndarray:
    """``num_events`` events of synthetic DVS128-Gesture-like recordings, one after another.

    Renders 6 s recordings of the 11 classes in turn with :mod:`evdown_torch.synthetic`
    (class ``k % 11``, seed ``seed + k``), each starting 6 s after the previous one, until
    there are enough events, and keeps the first ``num_events``.

    Returns:
        Structured array of :data:`DVS_DTYPE`, sorted by ``t`` (int64 microseconds).

    Example:
        >>> ev = gesture_stream(1000, sensor_size=(32, 32, 2))
        >>> len(ev), bool((np.diff(ev["t"]) >= 0).all())
        (1000, True)
    """
    from evdown_torch.synthetic import render_gesture

    n = check_positive_int("num_events", num_events)
    parts, total, k = [], 0, 0
    while total < n:
        part = render_gesture(k % 11, seed + k, sensor_size=sensor_size, duration_us=6_000_000)
        part["t"] += k * 6_000_000
        parts.append(part)
        total += len(part)
        k += 1
    return np.concatenate(parts)[:n].astype(DVS_DTYPE)


def with_pauses(events: np.ndarray, duration_us: int, *, bursts: int = 10) -> np.ndarray:
    """Spread a stream over ``duration_us`` as ``bursts`` equal bursts separated by pauses.

    The stream's span is cut into ``bursts`` equal time slices; slice ``k`` is shifted to start
    at ``k * duration_us / bursts``. The events, their order and the event rate inside each
    burst are unchanged; only the pauses between bursts grow.

    Args:
        events: structured array sorted by ``t`` (integer microseconds), starting at ``t >= 0``.
        duration_us: the new recording length, at least the stream's span.
        bursts: number of bursts (> 0).

    Returns:
        A new structured array of the same dtype.

    Example:
        >>> ev = dvs_like_stream(100, (32, 32, 2), duration_us=1000, seed=0)
        >>> int(with_pauses(ev, 100_000)["t"].max()) > 90_000
        True
    """
    bursts = check_positive_int("bursts", bursts)
    out = events.copy()
    if len(out) == 0:
        return out
    t = out["t"].astype(np.int64)
    t0 = int(t.min())
    span = int(t.max()) - t0 + 1
    if duration_us < span:
        raise ValueError(
            f"duration_us must be at least the stream's span {span}, got {duration_us}"
        )
    index = ((t - t0) * bursts) // span
    out["t"] = t + index * ((duration_us - span) // bursts)
    return out


def read_nmnist(path: str | Path) -> np.ndarray:
    """Read an N-MNIST ``.bin`` recording (40-bit events) without Tonic.

    Each event is 5 bytes, big-endian: x (8 bits), y (8 bits), polarity (1 bit), timestamp
    (23 bits, microseconds). An event with ``y == 240`` marks a timestamp overflow: it adds
    ``2**13`` to the timestamps of all later events and is not itself an event (as
    ``tonic.io.read_mnist_file`` reads it).

    Returns:
        Structured array of :data:`DVS_DTYPE`, in file order.
    """
    raw = np.fromfile(str(path), dtype=np.uint8)
    if raw.size % 5:
        raise ValueError(f"{str(path)!r} is not an N-MNIST file: {raw.size} bytes is not 5 * N")
    raw = raw.reshape(-1, 5).astype(np.int64)
    t = ((raw[:, 2] & 127) << 16) | (raw[:, 3] << 8) | raw[:, 4]
    overflow = raw[:, 1] == 240
    t = t + np.cumsum(overflow) * 2**13
    keep = ~overflow
    out = np.empty(int(keep.sum()), dtype=DVS_DTYPE)
    out["x"] = raw[keep, 0]
    out["y"] = raw[keep, 1]
    out["p"] = (raw[keep, 2] & 128) > 0
    out["t"] = t[keep]
    return out


def _stream_duration_s(events: np.ndarray) -> float:
    if len(events) == 0:
        return 0.0
    return float(int(events["t"].max()) - int(events["t"].min())) / 1e6


@dataclass(frozen=True)
class BenchInput:
    """An input stream of a benchmark (metadata; the events live in ``path``)."""

    name: str
    sensor_size: tuple[int, int, int]
    num_events: int
    duration_s: float
    source: str
    path: str


# ----------------------------------------------------------------------------- candidates


@dataclass(frozen=True)
class Candidate:
    """Something to benchmark: a method of this package or a peer.

    Attributes:
        name: the spec it was made from: a method's registry name, optionally with settings
            (``"lif:weight=1.5,reset_mechanism=zero"``), or a peer's name (see :data:`PEERS`).
        label: what the report calls it.
        peer: whether it is a peer (another library's transform).
        build: ``build(sensor_size, factor)`` returns a callable taking and returning a
            structured event array.
        dense_cost: for peers that build dense frames, ``dense_cost(sensor_size, factor,
            duration_us)`` estimates their ``(bytes, seconds per call)``, so that runs over
            the plan's budgets are skipped.
    """

    name: str
    label: str
    peer: bool
    build: Callable[[tuple[int, int, int], Any], Callable[[np.ndarray], np.ndarray]]
    dense_cost: Callable[[tuple[int, int, int], Any, float], tuple[float, float]] | None = None


def parse_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Split ``"NAME[:KEY=VALUE,KEY=VALUE...]"`` into the name and its settings.

    Values are Python literals where they parse as one, else strings; a comma starts a new
    setting only where ``KEY=`` follows it, so tuples are fine (``factor=(1, 2)``).

    Example:
        >>> parse_spec("lif:weight=1.5,reset_mechanism=zero")
        ('lif', {'weight': 1.5, 'reset_mechanism': 'zero'})
    """
    name, _, rest = spec.partition(":")
    settings: dict[str, Any] = {}
    for item in filter(None, re.split(r",\s*(?=[A-Za-z_]\w*\s*=)", rest)):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"a setting in {spec!r} must look like KEY=VALUE, got {item!r}")
        try:
            settings[key.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            settings[key.strip()] = value.strip()
    return name.strip(), settings


def _method_builder(name: str, settings: dict[str, Any]):
    def build(sensor_size, factor):
        return make_method(name, sensor_size, factor, **settings)

    return build


def _tonic_downsample(sensor_size, factor):
    import tonic

    fx, fy = check_factor(factor)
    return tonic.transforms.Downsample(spatial_factor=(1 / fx, 1 / fy))


def _tonic_event_downsampling(method: str):
    def build(sensor_size, factor):
        import tonic

        target = output_size(check_sensor_size(sensor_size), check_factor(factor))[:2]
        settings: dict[str, Any] = {"noise_threshold": PEER_NOISE_THRESHOLD}
        if method == "differentiator":
            settings["differentiator_time_bins"] = PEER_DIFFERENTIATOR_BINS
        return tonic.transforms.EventDownsampling(
            sensor_size=tuple(sensor_size), target_size=target, dt=PEER_DT_MS,
            downsampling_method=method, **settings,
        )

    return build


def _tonic_dense_cost(method: str):
    """Estimated (bytes, seconds per call) of Tonic's EventDownsampling on a stream.

    It builds dense frames of ``duration / dt`` steps over the output sensor and loops over
    them in Python, so its cost follows duration x area. The per-frame constants were
    measured on the development machine (Tonic 1.7): integrator about 14 bytes and
    100 us + 90 ns per output pixel and step, the differentiator about 64 bytes and three
    times the integrator's time.
    """

    def estimate(sensor_size, factor, duration_us):
        w, h, _ = output_size(check_sensor_size(sensor_size), check_factor(factor))
        frames = duration_us / (PEER_DT_MS * 1000) + 1
        seconds = frames * (100e-6 + 90e-9 * w * h)
        if method == "integrator":
            return frames * w * h * 14, seconds
        return frames * w * h * 64, 3 * seconds

    return estimate


#: Peer name -> label.
PEERS: dict[str, str] = {
    "tonic_downsample": "tonic Downsample",
    "tonic_integrator": "tonic EventDownsampling (integrator)",
    "tonic_differentiator": "tonic EventDownsampling (differentiator)",
}

_PEER_BUILDERS = {
    "tonic_downsample": (_tonic_downsample, None),
    "tonic_integrator": (_tonic_event_downsampling("integrator"),
                         _tonic_dense_cost("integrator")),
    "tonic_differentiator": (_tonic_event_downsampling("differentiator"),
                             _tonic_dense_cost("differentiator")),
}


def _tonic_available() -> bool:
    try:
        import tonic  # noqa: F401
    except ImportError:
        return False
    return True


def candidate(spec: str) -> Candidate:
    """The candidate a spec names: ``"NAME"`` or ``"NAME:KEY=VALUE,..."`` (see :func:`parse_spec`).

    A method runs with :data:`BENCH_SETTINGS` updated by the spec's settings; a peer takes
    no settings.

    Raises:
        ValueError: for an unknown name, settings given to a peer, a setting the method does
            not take, or a peer while Tonic is not installed.

    Example:
        >>> candidate("event_count:threshold=0.5").label
        'EventCount (threshold=0.5)'
    """
    name, settings = parse_spec(spec)
    if name in PEERS:
        if settings:
            raise ValueError(f"peer {name!r} takes no settings, got {spec!r}")
        if not _tonic_available():
            raise ValueError(f"peer {name!r} needs Tonic, which is not installed")
        build, dense = _PEER_BUILDERS[name]
        return Candidate(name, PEERS[name], True, build, dense)
    if name not in METHODS:
        raise ValueError(
            f"unknown method or peer {name!r}; expected one of {[*METHODS, *PEERS]}"
        )
    build = _method_builder(name, {**BENCH_SETTINGS.get(name, {}), **settings})
    build((8, 8, 2), 1)  # a setting the method does not take fails here
    text = ", ".join(f"{k}={v!r}" for k, v in settings.items())
    return Candidate(spec, METHODS[name].__name__ + (f" ({text})" if text else ""), False, build)


def candidates(names: Iterable[str] | None = None, *, peers: bool = True) -> list[Candidate]:
    """The candidates to benchmark: every method in ``METHODS``, then the peers.

    Args:
        names: specs of a subset of methods and peers, in this order (default: every method
            in ``METHODS``, then every peer); see :func:`candidate`.
        peers: with ``names=None``, include the Tonic peers (when Tonic is importable).

    Raises:
        ValueError: for a spec :func:`candidate` rejects.

    Example:
        >>> [c.name for c in candidates(["downsample", "funnelling"])]
        ['downsample', 'funnelling']
    """
    if names is None:
        names = [*METHODS, *(PEERS if peers and _tonic_available() else ())]
    return [candidate(spec) for spec in names]


# --------------------------------------------------------------------------------- timing


@dataclass(frozen=True)
class Timing:
    """Timed calls: the median wall-clock and process CPU seconds, and how many calls.

    On a shared machine the wall clock also counts waiting for a core; the CPU time does
    not, so the two agree when the machine was quiet.
    """

    seconds: float
    cpu_seconds: float
    runs: int


def time_call(
    fn: Callable[..., Any],
    *args: Any,
    repeats: int = 5,
    min_seconds: float = 0.0,
    max_repeats: int = 1000,
) -> tuple[Timing, Any]:
    """Time ``fn(*args)``: one warm-up call, then at least ``repeats`` timed calls.

    More calls (up to ``max_repeats``) are made until the timed ones add up to
    ``min_seconds`` of wall-clock time.

    Returns:
        ``(timing, result of the warm-up call)``.

    Example:
        >>> timing, result = time_call(sum, [1, 2, 3], repeats=5)
        >>> timing.runs, result, timing.seconds >= 0
        (5, 6, True)
    """
    repeats = check_positive_int("repeats", repeats)
    result = fn(*args)
    wall: list[float] = []
    cpu: list[float] = []
    while len(wall) < repeats or (sum(wall) < min_seconds and len(wall) < max_repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn(*args)
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return Timing(statistics.median(wall), statistics.median(cpu), len(wall)), result


# --------------------------------------------------------------------------------- memory


@dataclass(frozen=True)
class MemoryJob:
    """One peak-memory measurement, run in a fresh process by :func:`measure_memory`.

    Attributes:
        target: ``"package.module:function"`` or ``"path/to/file.py:function"``;
            ``function(**kwargs)`` prepares everything (loads, builds, warms up) and returns
            the zero-argument callable whose peak is measured (its return value comes back
            when it is a number or a string).
        kwargs: JSON-serialisable keyword arguments of ``function``.
    """

    target: str
    kwargs: dict[str, Any]


def candidate_job(spec: str, path: str, sensor_size: Sequence[int], factor: Any) -> MemoryJob:
    """The memory job of a candidate (see :func:`candidate`) once on a ``.npy`` stream."""
    return MemoryJob("evdown_torch.bench:prepare_candidate_call",
                     {"spec": spec, "path": str(path), "sensor_size": list(sensor_size),
                      "factor": factor})


def prepare_candidate_call(spec: str, path: str, sensor_size: Sequence[int],
                           factor: Any) -> Callable[[], Any]:
    """Load a stream, build the candidate, warm it up; return the call to measure.

    The warm-up is one call on the first 1000 events, so that one-time costs (lazy
    initialisation) are not counted as the call's.
    """
    events = np.load(path)
    fn = candidate(spec).build(tuple(sensor_size),
                               factor if isinstance(factor, int) else tuple(factor))
    with contextlib.suppress(Exception):  # a peer may reject a short slice; the call reports
        fn(events[:1000])
    return lambda: fn(events)


def _resolve(target: str) -> Callable[..., Callable[[], Any]]:
    where, sep, function = target.rpartition(":")
    if not sep or not where or not function:
        raise ValueError(f"target must look like MODULE:FUNCTION or FILE.py:FUNCTION, got "
                         f"{target!r}")
    if where.endswith(".py"):
        spec = importlib.util.spec_from_file_location(f"_bench_{Path(where).stem}", where)
        if spec is None or spec.loader is None:
            raise ValueError(f"cannot import {where!r}")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    else:
        module = importlib.import_module(where)
    return getattr(module, function)


def _proc_status_kib() -> dict[str, int]:
    values = {}
    with open("/proc/self/status") as status:
        for line in status:
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                values[key] = int(rest.split()[0])
    return values


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as refs:
            refs.write("5")
    except OSError:
        return False
    return True


def _peak_bytes() -> int:
    """Peak resident set of this process so far, in bytes.

    ``VmHWM`` where ``/proc`` exists (it starts afresh at ``exec``, and
    :func:`_reset_peak` resets it); else ``ru_maxrss``, which on Linux would also carry the
    peak of the process that spawned this one.
    """
    if Path("/proc/self/status").exists():
        return _proc_status_kib()["VmHWM"] * 1024
    import resource

    value = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(value) if sys.platform == "darwin" else int(value) * 1024


def _measure_here(job: MemoryJob, prepare: Callable[..., Callable[[], Any]]) -> dict[str, Any]:
    """Prepare the job, then measure the peak of its call in this process."""
    call = prepare(**job.kwargs)
    _reset_peak()
    before = _peak_bytes()
    start, start_cpu = time.perf_counter(), time.process_time()
    value = call()
    seconds, cpu = time.perf_counter() - start, time.process_time() - start_cpu
    out = {"added": _peak_bytes() - before, "peak": _peak_bytes(), "seconds": seconds,
           "cpu_seconds": cpu}
    if isinstance(value, (bool, int, float, str)):
        out["result"] = value
    return out


def _forked_measurement(job: MemoryJob, prepare, base_rss: int) -> dict[str, Any]:
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: prepare, measure one call, report, exit
        os.close(read_end)
        try:
            at_fork = _proc_status_kib()["VmRSS"] * 1024
            message = _measure_here(job, prepare)
            message["total"] = base_rss + message.pop("peak") - at_fork
        except BaseException as error:  # noqa: BLE001 - reported to the parent
            message = {"error": f"{type(error).__name__}: {error}"}
        os.write(write_end, json.dumps(message).encode())
        os._exit(0)
    os.close(write_end)
    chunks = []
    while chunk := os.read(read_end, 65536):
        chunks.append(chunk)
    os.close(read_end)
    _, status = os.waitpid(pid, 0)
    if not chunks:
        return {"error": f"the measuring process died (wait status {status})"}
    return json.loads(b"".join(chunks))


def _memory_worker(spec_path: str) -> None:
    """Entry point of the measuring process: runs the jobs of a JSON spec, prints results."""
    spec = json.loads(Path(spec_path).read_text())
    torch.set_num_threads(1)
    jobs = [MemoryJob(j["target"], j["kwargs"]) for j in spec["jobs"]]
    prepares: dict[str, Any] = {}  # imported before the baseline; an exception if it fails
    for job in jobs:
        if job.target not in prepares:
            try:
                prepares[job.target] = _resolve(job.target)
            except Exception as error:  # noqa: BLE001 - reported for the jobs that need it
                prepares[job.target] = error
    if any(job.kwargs.get("spec") in PEERS for job in jobs):
        import tonic  # noqa: F401 - imported before the baseline, like torch
    gc.collect()
    gc.freeze()  # forked children then never touch (copy) the imported objects
    fork = spec["fork"]
    base_rss = _proc_status_kib()["VmRSS"] * 1024 if fork else 0
    for job in jobs:
        if isinstance(prepares[job.target], Exception):
            error = prepares[job.target]
            result = {"error": f"{type(error).__name__}: {error}"}
        elif fork:
            result = _forked_measurement(job, prepares[job.target], base_rss)
        else:
            try:
                result = _measure_here(job, prepares[job.target])
                result["total"] = result.pop("peak")
            except Exception as error:  # noqa: BLE001 - reported to the parent
                result = {"error": f"{type(error).__name__}: {error}"}
        print("EVDOWN-MEM " + json.dumps(result), flush=True)


def _can_fork_measure() -> bool:
    return hasattr(os, "fork") and Path("/proc/self/status").exists()


def measure_memory(jobs: Sequence[MemoryJob], *, fork: bool | None = None) -> list[dict]:
    """Peak memory of each job's call, each measured in a fresh process.

    With ``fork`` (Linux; the default where possible) one fresh worker interpreter imports
    the jobs' modules, then forks one child per job: the child prepares the job, resets its
    peak resident set (``VmHWM``) and runs the call. Without it, every job runs in its own
    fresh interpreter.

    Args:
        jobs: the measurements to make.
        fork: see above (default: where possible).

    Returns:
        One dict per job: ``{"added": bytes, "total": bytes, "seconds": s,
        "cpu_seconds": s}`` or ``{"error": message}``. *added* is the peak resident set
        during the call minus the resident set just before it; *total* is the peak of a
        fresh process that imports, prepares and calls (the worker's resident set after
        imports plus the child's growth up to its peak); *seconds* and *cpu_seconds* are the
        call's wall-clock and CPU time; *result* is the call's return value when it is a
        number or a string.
    """
    if not jobs:
        return []
    fork = _can_fork_measure() if fork is None else fork
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = "1"
    groups = [list(jobs)] if fork else [[job] for job in jobs]
    results: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="evdown-mem-") as tmp:
        for i, group in enumerate(groups):
            spec = Path(tmp) / f"spec{i}.json"
            spec.write_text(json.dumps({"fork": fork, "jobs": [asdict(j) for j in group]}))
            code = ("import sys; from evdown_torch.bench import _memory_worker; "
                    "_memory_worker(sys.argv[1])")
            done = subprocess.run([sys.executable, "-c", code, str(spec)], env=env,
                                  capture_output=True, text=True, check=False)
            lines = [json.loads(line[len("EVDOWN-MEM "):]) for line in done.stdout.splitlines()
                     if line.startswith("EVDOWN-MEM ")]
            if len(lines) < len(group):
                tail = done.stderr.strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
                lines += [{"error": f"memory worker failed: {tail[0]}"}] * (len(group) - len(lines))
            results.extend(lines)
    return results


# ---------------------------------------------------------------------------------- plan


@dataclass(frozen=True)
class Plan:
    """Sizes of one benchmark run."""

    short: bool
    headline_events: int
    large_events: int
    factors: tuple[int, ...]
    repeats: int
    scaling_repeats: int
    events_sweep: tuple[int, ...]
    sensor_sweep: tuple[tuple[int, int], ...]
    sweep_events: int
    duration_sweep_s: tuple[float, ...]
    min_seconds: float
    peer_seconds_budget: float


def make_plan(short: bool = False, events: int | None = None, repeats: int | None = None) -> Plan:
    """The run's sizes: full (goal-sized inputs, 10k to 10M events) or short (< 2 minutes).

    ``events`` caps every stream's size (for quick checks); ``repeats`` sets the timed calls of
    the method table (at least 5 by default; scaling points use 3).
    """
    if short:
        plan = Plan(True, 200_000, 200_000, (2, 4), 5, 3, (10_000, 100_000),
                    ((128, 128), (1280, 720)), 100_000, (1.0, 10.0), 0.05, 2.0)
    else:
        plan = Plan(False, 1_000_000, 10_000_000, (2, 4), 5, 3,
                    (10_000, 100_000, 1_000_000, 10_000_000),
                    ((128, 128), (346, 260), (640, 480), (1280, 720)), 1_000_000,
                    (1.0, 10.0, 100.0, 1000.0), 0.5, 30.0)
    if events is not None:
        cap = check_positive_int("events", events)
        sweep = tuple(n for n in plan.events_sweep if n <= cap)
        if len(sweep) < 2:
            sweep = (max(cap // 10, 1), cap)
        plan = replace(plan, headline_events=cap, large_events=min(plan.large_events, cap),
                       events_sweep=sweep, sweep_events=min(plan.sweep_events, cap))
    if repeats is not None:
        r = check_positive_int("repeats", repeats)
        plan = replace(plan, repeats=r, scaling_repeats=min(plan.scaling_repeats, r))
    return plan


# ----------------------------------------------------------------------------------- run


@dataclass
class Measurement:
    """One candidate on one input at one factor.

    ``section`` is ``"methods"`` for the method table or the sweep's name (``"events"``,
    ``"sensor"``, ``"duration"``); ``x`` is the sweep's value. Times in seconds, memory in
    bytes; ``None`` where not measured (``note`` says why).
    """

    section: str
    input: str
    x: float | None
    candidate: str
    label: str
    peer: bool
    factor: Any
    events_in: int
    events_out: int | None = None
    seconds: float | None = None
    cpu_seconds: float | None = None
    runs: int = 0
    peak_added: int | None = None
    peak_total: int | None = None
    note: str = ""

    @property
    def rate(self) -> float | None:
        """Input events per second (``None`` when not timed)."""
        if self.seconds is None:
            return None
        return self.events_in / self.seconds if self.seconds > 0 else math.inf


@dataclass
class BenchResults:
    """Everything one run measured."""

    plan: Plan
    machine: dict[str, str]
    inputs: list[BenchInput]
    measurements: list[Measurement]
    candidates: list[tuple[str, str, bool]]
    notes: list[str] = field(default_factory=list)
    elapsed_s: float = 0.0

    def input(self, name: str) -> BenchInput | None:
        """The input called ``name``."""
        return next((i for i in self.inputs if i.name == name), None)

    def find(self, section: str, input_name: str | None, candidate: str, factor: Any,
             x: float | None = None) -> Measurement | None:
        """The measurement of ``candidate`` on an input (or sweep point ``x``) at ``factor``."""
        for m in self.measurements:
            if (m.section == section and m.candidate == candidate and m.factor == factor
                    and (input_name is None or m.input == input_name)
                    and (x is None or m.x == x)):
                return m
        return None


def machine_description() -> dict[str, str]:
    """CPU, cores, memory and library versions of this machine."""
    cpu = platform.processor() or platform.machine()
    memory = ""
    try:
        with open("/proc/cpuinfo") as info:
            cpu = next((line.split(":", 1)[1].strip() for line in info
                        if line.startswith("model name")), cpu)
        with open("/proc/meminfo") as info:
            kib = int(next(line.split()[1] for line in info if line.startswith("MemTotal")))
            memory = f"{kib / 2**20:.0f} GiB"
    except OSError:
        pass
    try:
        import tonic

        tonic_version = tonic.__version__
    except ImportError:
        tonic_version = "not installed"
    return {
        "cpu": cpu, "cores": str(os.cpu_count()), "memory": memory,
        "python": platform.python_version(), "torch": torch.__version__,
        "numpy": np.__version__, "tonic": tonic_version, "threads": "1",
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }


class _Runner:
    def __init__(self, plan: Plan, cands: list[Candidate], memory: bool, tmp: Path) -> None:
        self.plan, self.cands, self.memory, self.tmp = plan, cands, memory, tmp
        self.inputs: list[BenchInput] = []
        self.measurements: list[Measurement] = []
        self.jobs: list[tuple[Measurement, MemoryJob]] = []

    def add_input(self, name: str, events: np.ndarray, sensor_size, source: str) -> BenchInput:
        path = self.tmp / f"{name}.npy"
        np.save(path, events)
        inp = BenchInput(name, tuple(sensor_size), len(events), _stream_duration_s(events),
                         source, str(path))
        self.inputs.append(inp)
        return inp

    def measure(self, section: str, inp: BenchInput, events: np.ndarray, factor, repeats: int,
                x: float | None = None) -> None:
        for cand in self.cands:
            m = Measurement(section, inp.name, x, cand.name, cand.label, cand.peer, factor,
                            len(events))
            self.measurements.append(m)
            if cand.dense_cost is not None:
                need, seconds = cand.dense_cost(inp.sensor_size, factor, inp.duration_s * 1e6)
                if need > PEER_MEMORY_BUDGET:
                    m.note = f"skipped: dense frames need ~{need / 1e9:.1f} GB"
                    continue
                if seconds > self.plan.peer_seconds_budget:
                    m.note = f"skipped: ~{seconds:.0f} s per call"
                    continue
            try:
                fn = cand.build(inp.sensor_size, factor)
                timing, out = time_call(fn, events, repeats=repeats,
                                        min_seconds=self.plan.min_seconds)
                m.seconds, m.cpu_seconds, m.runs = timing.seconds, timing.cpu_seconds, timing.runs
                m.events_out = len(out)
            except Exception as error:  # noqa: BLE001 - a failing peer is a result too
                m.note = f"failed: {type(error).__name__}: {error}"[:200]
                continue
            _log(f"{section} {inp.name} f={factor} {cand.name}: {m.rate / 1e6:.2f} M events/s")
            if self.memory:
                self.jobs.append((m, candidate_job(cand.name, inp.path, inp.sensor_size, factor)))

    def measure_memory(self) -> None:
        if not self.jobs:
            return
        _log(f"peak memory: {len(self.jobs)} measurements in a fresh process")
        for (m, _), result in zip(self.jobs, measure_memory([job for _, job in self.jobs])):
            if "error" in result:
                m.note = (m.note + "; " if m.note else "") + f"memory: {result['error']}"[:200]
            else:
                m.peak_added, m.peak_total = int(result["added"]), int(result["total"])


def _headline_stream(plan: Plan, seed: int) -> tuple[np.ndarray, str]:
    events = gesture_stream(plan.headline_events, seed=seed)
    return events, (f"evdown_torch.synthetic gestures (6 s recordings of the 11 classes in "
                    f"turn, seed {seed}), first {len(events):,} events")


def run_benchmark(
    *,
    short: bool = False,
    inputs: Sequence[str | Path] = (),
    sensor_size: tuple[int, int, int] | None = None,
    events: int | None = None,
    repeats: int | None = None,
    methods: Sequence[str] | None = None,
    scaling: bool = True,
    memory: bool = True,
    seed: int = 0,
) -> BenchResults:
    """Run the benchmark: the method table, the scaling sweeps and the peak memory.

    Args:
        short: the short mode (small inputs, two points per sweep; under 2 minutes).
        inputs: extra ``.npy`` structured event arrays to add to the method table.
        sensor_size: the sensor of those files (default: largest coordinates + 1, 2 polarities).
        events: cap on every stream's number of events (quick checks).
        repeats: timed calls per measurement of the method table (default 5).
        methods: a subset of method and peer names (default: all of them).
        scaling: run the scaling sweeps.
        memory: measure peak memory.
        seed: seed of the synthetic streams.

    Returns:
        The results, for :func:`write_report`.
    """
    plan = make_plan(short, events, repeats)
    extra = [(Path(p), load_npy_events(p)) for p in inputs]
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    cands = candidates(methods)
    notes = []
    if not _tonic_available():
        notes.append("Tonic is not installed: the peers are not measured.")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    start = time.perf_counter()
    try:
        with tempfile.TemporaryDirectory(prefix="evdown-bench-") as tmp:
            run = _Runner(plan, cands, memory, Path(tmp))
            events_, source = _headline_stream(plan, seed)
            inp = run.add_input("gesture", events_, (128, 128, 2), source)
            for factor in plan.factors:
                run.measure("methods", inp, events_, factor, plan.repeats)
            if NMNIST_FILE.exists():
                events_ = read_nmnist(NMNIST_FILE)
                inp = run.add_input("nmnist", events_, (34, 34, 2),
                                    f"real N-MNIST sample ({NMNIST_FILE.name})")
                for factor in plan.factors:
                    run.measure("methods", inp, events_, factor, plan.repeats)
            else:
                notes.append(f"{NMNIST_FILE} is absent: no real recording in the method table.")
            for path, events_ in extra:
                size = sensor_size or (int(events_["x"].max()) + 1 if len(events_) else 1,
                                       int(events_["y"].max()) + 1 if len(events_) else 1, 2)
                inp = run.add_input(path.stem, events_, size, f"file {path}")
                for factor in plan.factors:
                    run.measure("methods", inp, events_, factor, plan.repeats)
            duration = max(int(plan.large_events / LARGE_RATE * 1e6), 1)
            events_ = dvs_like_stream(plan.large_events, (1280, 720, 2), duration_us=duration,
                                      seed=seed + 1, num_objects=12)
            inp = run.add_input("large", events_, (1280, 720, 2),
                                f"dvs_like_stream, 12 bars, {duration / 1e6:.2f} s")
            run.measure("methods", inp, events_, 4, plan.repeats)
            del events_
            if scaling:
                _sweeps(run, plan, seed)
            run.measure_memory()
    finally:
        torch.set_num_threads(threads)
    return BenchResults(plan, machine_description(), run.inputs, run.measurements,
                        [(c.name, c.label, c.peer) for c in cands], notes,
                        time.perf_counter() - start)


def _sweeps(run: _Runner, plan: Plan, seed: int) -> None:
    for n in plan.events_sweep:
        duration = max(int(n / EVENTS_SWEEP_RATE * 1e6), 1)
        events = dvs_like_stream(n, (128, 128, 2), duration_us=duration, seed=seed + 2)
        inp = run.add_input(f"events-{n}", events, (128, 128, 2),
                            f"dvs_like_stream, {EVENTS_SWEEP_RATE / 1e3:.0f}k events/s")
        run.measure("events", inp, events, 4, plan.scaling_repeats, x=n)
    n = plan.sweep_events
    for w, h in plan.sensor_sweep:
        objects = max(4, round(4 * math.sqrt(w * h / 128**2)))
        events = dvs_like_stream(n, (w, h, 2), duration_us=2_000_000, seed=seed + 3,
                                 num_objects=objects)
        inp = run.add_input(f"sensor-{w}x{h}", events, (w, h, 2),
                            f"dvs_like_stream, {objects} bars, 2 s")
        run.measure("sensor", inp, events, 4, plan.scaling_repeats, x=w * h)
    base_s = plan.duration_sweep_s[0]
    base = dvs_like_stream(n, (128, 128, 2), duration_us=int(base_s * 1e6), seed=seed + 4)
    for seconds in plan.duration_sweep_s:
        events = with_pauses(base, int(seconds * 1e6))
        inp = run.add_input(f"duration-{seconds:g}s", events, (128, 128, 2),
                            f"dvs_like_stream, {n / base_s / 1e3:.0f}k events/s in 10 bursts")
        run.measure("duration", inp, events, 4, plan.scaling_repeats, x=seconds)


# ----------------------------------------------------------------------------- the goals


@dataclass(frozen=True)
class Goal:
    """A speed or memory goal stated in an issue.

    ``kind`` is ``"rate"`` (events/s on the headline stream at factor 4, ``value`` the
    minimum), ``"peer"`` (throughput ratio to peer ``peer``, ``value`` the minimum) or
    ``"memory"`` (process peak on the large stream at factor 4, ``value`` the maximum bytes).
    """

    issue: int
    method: str
    kind: str
    value: float
    text: str
    peer: str = ""


GOALS: tuple[Goal, ...] = (
    Goal(2, "downsample", "peer", 0.5, ">= 0.5x tonic Downsample's throughput",
         "tonic_downsample"),
    Goal(2, "funnelling", "rate", 10e6, ">= 10 M events/s"),
    Goal(3, "event_count", "rate", 10e6, ">= 10 M events/s"),
    Goal(3, "linear", "rate", 3e6, ">= 3 M events/s"),
    Goal(3, "cubic", "rate", 1e6, ">= 1 M events/s"),
    Goal(5, "lif", "rate", 2e6, ">= 2 M events/s (dt = 1 ms)"),
    *(Goal(3, name, "memory", 4e9, "peak < 4 GB on 1280x720, 10M events")
      for name in ("downsample", "funnelling", "event_count", "linear", "cubic", "lif")),
)


def evaluate_goals(results: BenchResults) -> list[dict[str, str]]:
    """Each goal of a method that was measured: its figure and whether it is met."""
    rows = []
    headline, large = results.input("gesture"), results.input("large")
    measured = {m.candidate for m in results.measurements}
    for goal in GOALS:
        if goal.method not in measured:
            continue
        row = {"issue": str(goal.issue), "method": goal.method, "goal": goal.text,
               "measured": "n/a", "status": ""}
        if goal.kind == "memory":
            m = results.find("methods", "large", goal.method, 4)
            small = large is not None and large.num_events < 10_000_000
            if m is None or m.peak_total is None:
                row["status"] = "not measured" + (f" ({m.note})" if m and m.note else "")
            else:
                row["measured"] = f"{m.peak_total / 1e9:.2f} GB"
                over = m.peak_total / goal.value - 1
                row["status"] = "met" if over <= 0 else f"missed by {over * 100:.0f}% (over)"
                if small:
                    row["status"] += f" (indicative: {large.num_events:,} events, not 10M)"
        else:
            m = results.find("methods", "gesture", goal.method, 4)
            small = headline is not None and headline.num_events < 1_000_000
            if m is None or m.rate is None:
                row["status"] = "not measured" + (f" ({m.note})" if m and m.note else "")
            elif goal.kind == "rate":
                cpu_rate = m.events_in / m.cpu_seconds if m.cpu_seconds else math.inf
                row["measured"] = (f"{m.rate / 1e6:.2f} M events/s ({cpu_rate / 1e6:.2f} on "
                                   "CPU time)")
                row["status"] = _status(m.rate >= goal.value, m.rate / goal.value)
                if m.rate < goal.value <= cpu_rate:
                    row["status"] += " (met on CPU time: the call waited for a busy core)"
            else:
                peer = results.find("methods", "gesture", goal.peer, 4)
                if peer is None or peer.rate is None:
                    row["status"] = "not measured (peer absent)"
                else:
                    ratio = m.rate / peer.rate
                    row["measured"] = f"{ratio:.2f}x"
                    row["status"] = _status(ratio >= goal.value, ratio / goal.value)
            paper = PAPER_SECONDS_PER_100K.get(goal.method)
            if m is not None and m.rate is not None and paper and goal.kind == "rate":
                row["measured"] += f"; {m.rate * paper / 1e5:,.0f}x the paper's code"
            if small and row["measured"] != "n/a":
                row["status"] += (f" (indicative: {headline.num_events:,} events, "
                                  "the goal's stream has 1M)")
        rows.append(row)
    return rows


def _status(met: bool, margin: float) -> str:
    return "met" if met else f"missed by {(1 - margin) * 100:.0f}%"


# ---------------------------------------------------------------------------------- report


def _num(value: float | None, digits: int = 3) -> str:
    """``digits`` significant digits (more for large numbers), no exponent; n/a for None."""
    if value is None:
        return "n/a"
    if not math.isfinite(value):
        return "inf"
    if value == 0:
        return "0"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(value))))
    return f"{value:.{decimals}f}"


def _mb(value: int | None) -> str:
    return "n/a" if value is None else _num(value / 1e6)


def _factor_text(factor: Any) -> str:
    return str(factor) if isinstance(factor, int) else f"{factor[0]}x{factor[1]}"


def method_table(results: BenchResults, input_name: str) -> str:
    """The Markdown table of every candidate on one input (all factors)."""
    peers = [(n, label) for n, label, is_peer in results.candidates if is_peer]
    head = ["method", "factor", "events in", "events out", "out / in", "median ms", "CPU ms",
            "runs", "M events/s", *[f"x {label}" for _, label in peers], "peak added MB",
            "peak process MB", "note"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rows = [m for m in results.measurements if m.section == "methods" and m.input == input_name]
    for m in rows:
        ratios = []
        for peer, _ in peers:
            ref = results.find("methods", input_name, peer, m.factor)
            ok = ref is not None and ref.rate and m.rate
            ratios.append(_num(m.rate / ref.rate) if ok else "n/a")
        share = m.events_out / m.events_in if m.events_out is not None and m.events_in else None
        cells = [m.label, _factor_text(m.factor), str(m.events_in),
                 "n/a" if m.events_out is None else str(m.events_out), _num(share),
                 _num(None if m.seconds is None else m.seconds * 1e3),
                 _num(None if m.cpu_seconds is None else m.cpu_seconds * 1e3), str(m.runs),
                 _num(None if m.rate is None else m.rate / 1e6), *ratios,
                 _mb(m.peak_added), _mb(m.peak_total), m.note.replace("|", "/")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


_SWEEPS = {
    "events": ("Cost against the number of events", "events",
               f"128x128 sensor, {EVENTS_SWEEP_RATE / 1e3:.0f}k events/s (duration grows "
               "with the count), factor 4"),
    "sensor": ("Cost against the sensor size", "sensor pixels (W x H)",
               "fixed event count and duration (2 s), factor 4"),
    "duration": ("Cost against the recording duration", "duration (s)",
                 "fixed event count on 128x128; the events come in 10 bursts at a fixed rate "
                 "and the pauses between them grow; factor 4"),
}


def sweep_table(results: BenchResults, section: str, value: str) -> str:
    """Markdown table of one sweep: rows are candidates, columns the sweep's points.

    ``value`` is ``"rate"`` (M events/s) or ``"memory"`` (peak added MB).
    """
    points = sorted({m.x for m in results.measurements if m.section == section})
    names = {m.input: m.x for m in results.measurements if m.section == section}
    by_x = {x: name for name, x in names.items()}
    labels = [_point_label(section, by_x[x], x) for x in points]
    lines = ["| method | " + " | ".join(labels) + " |", "|" + "---|" * (len(points) + 1)]
    for name, label, _ in results.candidates:
        cells = []
        for x in points:
            m = results.find(section, None, name, 4, x=x)
            if m is None:
                cells.append("n/a")
            elif value == "rate":
                cells.append("skipped" if m.note.startswith("skipped") else
                             _num(None if m.rate is None else m.rate / 1e6))
            else:
                cells.append("skipped" if m.note.startswith("skipped") else _mb(m.peak_added))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _point_label(section: str, input_name: str, x: float) -> str:
    if section == "events":
        return f"{int(x):,}"
    if section == "sensor":
        return input_name.removeprefix("sensor-")
    return f"{x:g} s"


def write_report(results: BenchResults, out_dir: str | Path, *, command: str = "") -> list[Path]:
    """Write ``report.md``, ``results.json`` and the PNG plots to ``out_dir``.

    Returns:
        The paths written. Without matplotlib the plots are left out and the report says so.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "results.json"]
    (out / "results.json").write_text(json.dumps(_as_json(results), indent=1))
    plots: list[Path] = []
    notes = list(results.notes)
    try:
        plots = _plots(results, out)
    except ImportError:
        message = ("matplotlib is not installed: the report has no plots "
                   "(pip install 'evdown_torch[plot]' to get them).")
        _log(message)
        notes.append(message)
    written += plots
    (out / "report.md").write_text(_markdown(results, plots, notes, command))
    written.insert(0, out / "report.md")
    return written


def _as_json(results: BenchResults) -> dict:
    return {
        "plan": asdict(results.plan), "machine": results.machine,
        "inputs": [asdict(i) for i in results.inputs],
        "candidates": [{"name": n, "label": label, "peer": p}
                       for n, label, p in results.candidates],
        "measurements": [{**asdict(m), "rate": m.rate} for m in results.measurements],
        "goals": evaluate_goals(results), "notes": results.notes,
        "elapsed_s": results.elapsed_s,
    }


def load_results(path: str | Path) -> BenchResults:
    """Read back the ``results.json`` that :func:`write_report` wrote (to re-render a report).

    Example:
        >>> import tempfile
        >>> r = run_benchmark(short=True, events=300, methods=["downsample"], scaling=False,
        ...                   memory=False)
        >>> with tempfile.TemporaryDirectory() as out:
        ...     _ = write_report(r, out)
        ...     again = load_results(Path(out) / "results.json")
        >>> again.measurements == r.measurements and again.plan == r.plan
        True
    """
    data = json.loads(Path(path).read_text())

    def tuples(value):
        return tuple(tuples(v) for v in value) if isinstance(value, list) else value

    plan = Plan(**{k: tuples(v) for k, v in data["plan"].items()})
    inputs = [BenchInput(**{**i, "sensor_size": tuple(i["sensor_size"])})
              for i in data["inputs"]]
    names = {f.name for f in fields(Measurement)}
    measurements = [Measurement(**{k: tuples(v) for k, v in m.items() if k in names})
                    for m in data["measurements"]]
    return BenchResults(plan, data["machine"], inputs, measurements,
                        [(c["name"], c["label"], c["peer"]) for c in data["candidates"]],
                        data["notes"], data["elapsed_s"])


def _markdown(results: BenchResults, plots: list[Path], notes: list[str], command: str) -> str:
    mc, plan = results.machine, results.plan
    lines = [
        "# evdown_torch benchmark report", "",
        f"Mode: {'short' if plan.short else 'full'}; {mc['date']}; took "
        f"{results.elapsed_s:.0f} s." + (f" Command: `{command}`." if command else ""), "",
        f"Machine: {mc['cpu']}, {mc['cores']} cores, {mc['memory']}; Python {mc['python']}, "
        f"torch {mc['torch']} ({mc['threads']} thread), NumPy {mc['numpy']}, "
        f"Tonic {mc['tonic']}.", "",
        "## What is measured", "",
        "- **Time**: wall-clock time of one call of the transform on a Tonic structured array "
        "(validation and conversions included), `torch.set_num_threads(1)`; median of "
        f"{plan.repeats} or more calls after one warm-up call (more until the calls add up to "
        f"{plan.min_seconds:g} s; {plan.scaling_repeats} or more in the scaling sweeps). "
        "*CPU ms* is the median process CPU time of the same calls: where it is well below the "
        "wall-clock time, the call waited for a core on a busy machine. Every candidate "
        "runs in this one process and run. **M events/s** is input events / median time; "
        "**x peer** is the candidate's throughput divided by the peer's (above 1: faster).",
        "- **Peak memory** (MB = 10^6 bytes), per measurement in a fresh process forked from a "
        "worker that has only imported the libraries: *added* is the peak resident set during "
        "the one call minus the resident set just before it (input loaded); *process* is the "
        "peak resident set of a fresh process that imports, loads the input and runs the "
        "method once (interpreter and libraries included; the worker imports torch and "
        "Tonic for every candidate, so a peer's figure includes torch too). Both are taken "
        "after a warm-up call on the first 1000 events, so one-time initialisation is not "
        "counted as the call's.",
        f"- **Peers**: `tonic.transforms.Downsample(spatial_factor=1/f)`; "
        f"`tonic.transforms.EventDownsampling(sensor_size, target_size=ceil(size/f), "
        f"dt={PEER_DT_MS:g} ms, noise_threshold={PEER_NOISE_THRESHOLD})`, integrator and "
        f"differentiator (differentiator_time_bins={PEER_DIFFERENTIATOR_BINS}). "
        "EventDownsampling builds dense frames of duration / dt steps; a run whose frames "
        f"would exceed {PEER_MEMORY_BUDGET / 1e9:.0f} GB is skipped.",
        "- **Method settings** (the defaults, except those in `BENCH_SETTINGS`): "
        + "; ".join(f"{name}: {text}" for name, text in _settings_text(results)) + ".",
    ]
    if notes:
        lines += ["", "Notes:", *[f"- {n}" for n in notes]]
    lines += ["", "## Inputs", "", "| input | sensor | events | duration s | source |",
              "|---|---|---|---|---|"]
    for i in results.inputs:
        lines.append(f"| {i.name} | {i.sensor_size[0]}x{i.sensor_size[1]} | {i.num_events} | "
                     f"{i.duration_s:.3f} | {i.source} |")
    lines += ["", "## Goals", "",
              "Rate goals: the `gesture` stream at factor 4, one thread. Memory goal: the "
              "`large` stream at factor 4, process peak.", "",
              "| issue | method | goal | measured | status |", "|---|---|---|---|---|"]
    for g in evaluate_goals(results):
        lines.append(f"| {g['issue']} | {g['method']} | {g['goal']} | {g['measured']} | "
                     f"{g['status']} |")
    lines += ["", "## Methods and peers"]
    for i in results.inputs:
        if any(m.section == "methods" and m.input == i.name for m in results.measurements):
            lines += ["", f"### {i.name}: {i.sensor_size[0]}x{i.sensor_size[1]}, "
                      f"{i.num_events:,} events, {i.duration_s:.2f} s", "",
                      method_table(results, i.name)]
    sections = [s for s in _SWEEPS if any(m.section == s for m in results.measurements)]
    if sections:
        lines += ["", "## Scaling"]
    for s in sections:
        title, _, setup = _SWEEPS[s]
        lines += ["", f"### {title}", "", f"{setup}.", "", "Throughput, M events/s:", "",
                  sweep_table(results, s, "rate"), "", "Peak added memory, MB:", "",
                  sweep_table(results, s, "memory")]
        plot = next((p for p in plots if p.name == f"scaling_{s}.png"), None)
        if plot is not None:
            lines += ["", f"![{title}]({plot.name})"]
    return "\n".join(lines) + "\n"


def _settings_text(results: BenchResults) -> list[tuple[str, str]]:
    out = []
    for name, _, peer in results.candidates:
        if peer:
            continue
        transform = candidate(name).build((128, 128, 2), 4)
        keys = method_settings(parse_spec(name)[0])
        values = [f"{key}={getattr(transform, key)!r}" for key in keys]
        out.append((name, ", ".join(values) or "no settings"))
    return out


def _plots(results: BenchResults, out: Path) -> list[Path]:
    from matplotlib.figure import Figure

    paths = []
    for s, (title, xlabel, setup) in _SWEEPS.items():
        rows = [m for m in results.measurements if m.section == s]
        if not rows:
            continue
        fig = Figure(figsize=(13, 4.2), layout="constrained")
        rate_ax, mem_ax = fig.subplots(1, 2)
        for name, label, peer in results.candidates:
            mine = sorted((m for m in rows if m.candidate == name), key=lambda m: m.x)
            style = dict(marker="o", linestyle="--" if peer else "-", label=label)
            xs = [m.x for m in mine if m.rate is not None]
            rate_ax.plot(xs, [m.rate / 1e6 for m in mine if m.rate is not None], **style)
            xs = [m.x for m in mine if m.peak_added is not None]
            mem_ax.plot(xs, [max(m.peak_added, 1e4) / 1e6 for m in mine
                             if m.peak_added is not None], **style)
        for ax, ylabel in ((rate_ax, "throughput (M events/s)"),
                           (mem_ax, "peak added memory (MB)")):
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            ax.grid(True, which="both", alpha=0.3)
        fig.legend(*rate_ax.get_legend_handles_labels(), loc="outside right center", fontsize=8)
        fig.suptitle(f"{title} ({setup})", fontsize=9)
        path = out / f"scaling_{s}.png"
        fig.savefig(path, dpi=100)
        paths.append(path)
    return paths


# ------------------------------------------------------------------------------------- cli


def run_from_args(args: argparse.Namespace) -> int:
    """The ``evdown bench`` command (see :func:`evdown_torch.cli.build_parser`)."""
    if args.events is not None:
        check_positive_int("--events", args.events)
    results = run_benchmark(
        short=args.short, inputs=args.input or (), sensor_size=args.sensor_size,
        events=args.events, repeats=args.repeats, methods=args.methods,
        scaling=not args.no_scaling, memory=not args.no_memory,
    )
    command = "evdown bench " + " ".join(sys.argv[2:]) if len(sys.argv) > 1 else ""
    written = write_report(results, args.out, command=command)
    headline = results.input("gesture")
    print(f"gesture: {headline.sensor_size[0]}x{headline.sensor_size[1]}, "
          f"{headline.num_events:,} events\n{method_table(results, 'gesture')}")
    print(f"evdown bench: {len(results.measurements)} measurements in "
          f"{results.elapsed_s:.0f} s; wrote {', '.join(str(p) for p in written)}")
    for g in evaluate_goals(results):
        print(f"  issue {g['issue']} {g['method']}: {g['goal']}: {g['measured']} -> "
              f"{g['status']}")
    return 0

