"""``evdown bench --realtime``: can a method keep up with a live sensor, and with what delay?

A recording is replayed through each method's streaming session (:meth:`session`) in chunks
of fixed *stream* time (1, 2 and 10 ms by default), at the recording's own rate and retimed to
25 M events/s (a fast sensor's peak: its timestamps are compressed by the ratio of the rates,
so the same events arrive faster). Per method, rate and chunk size it reports:

* the wall-clock processing time of each chunk (median and 99th percentile), on one thread;
* the **latency budget**: the method's algorithmic delay (its ``algorithmic_delay()``) plus
  the chunk's duration (an event waits up to that long for its chunk to close) plus the 99th
  percentile of the processing time, i.e. how late after it happened an event's output is
  in hand in 99 % of the chunks; only where the method keeps up (else the queue grows without
  bound and no budget holds);
* whether the method **keeps up** (99th percentile below the chunk's duration) and the
  largest input rate it **sustains**: the replayed rate times the chunk's duration over the
  99th percentile, i.e. the rate at which the 99th percentile would reach the chunk's
  duration if a chunk's time grew in proportion to its events (an extrapolation from the
  replayed rate, exact at it, conservative where a fixed cost per call dominates);
* the sustained rate over EventCount's in the same run, at the same rate and chunk size
  (column "x EventCount"; EventCount is the cheapest method that also cuts the rate);
* the sustained rate over the *floor*'s, in the same run and chunks (column "x floor"): the
  floor (:mod:`evdown_torch.bench.floor`, replayed first, with Numba) reads each event and
  counts it in its output region, the one pass no downscaler can avoid;
* the same 99th percentile in process CPU time, which a busy machine does not inflate;
* for methods whose output lags their input (LinearEstimation and CubicEstimation with
  ``max_delay``), the **output delay** of each output event a chunk returned: the end of that
  chunk (when a live system has it) minus the event's time, in stream time (events the final
  flush returns are decided by the end of the stream and have no delay).

Only the chunks of a replay are timed (the recording is loaded and retimed first); the first
chunk's call warms up and the stream's last chunk (cut short by the end of the recording) is
processed but not counted. A method without a session of the common shape
(:class:`~evdown_torch.transforms.Session`) is skipped with a note.

**Memory allocator.** With glibc's default settings, the memory a chunk's temporaries free
goes back to the system, and the next chunk pays a page fault for every 4 KiB it touches
again: on a small VM that is a large share of a short chunk's time. A live process keeps its
memory instead, with glibc's documented environment variables (no code change), e.g.
``MALLOC_TRIM_THRESHOLD_=1073741824 MALLOC_MMAP_THRESHOLD_=33554432``. The report's header
names the settings it ran under (:func:`allocator_settings`) and the JSON gives the minor page
faults of the median chunk, so runs under both settings can be told apart and compared.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from evdown_torch.bench.floor import RegionFloor
from evdown_torch.checks import check_positive_int
from evdown_torch.threads import torch_threads
from evdown_torch.transforms import Chain, Streaming, TemporalFunnelling
from evdown_torch.transforms.registry import METHODS, make_method

__all__ = [
    "ALLOCATOR_VARIABLES",
    "FLOOR",
    "REALTIME_CHUNKS_US",
    "REALTIME_METHODS",
    "REALTIME_RATE",
    "ReplayResult",
    "allocator_settings",
    "chunk_bounds_us",
    "minor_faults",
    "realtime_benchmark",
    "realtime_markdown",
    "replay",
    "retime",
    "write_realtime_report",
]

#: A fast sensor's peak event rate (events per second).
REALTIME_RATE = 25_000_000.0
#: Chunk durations in stream time (microseconds).
REALTIME_CHUNKS_US = (1_000, 2_000, 10_000)
#: Bounded delay of the estimators in the replay (microseconds).
REALTIME_MAX_DELAY_US = 1_000
#: The replay's settings where a method's defaults do not stream or do not fit a live sensor:
#: a bounded delay for the estimators, 1 ms steps for LIF pooling and temporal funnelling.
REALTIME_SETTINGS: dict[str, dict[str, Any]] = {
    "temporal": {"dt": 1000},
    "linear": {"max_delay": REALTIME_MAX_DELAY_US},
    "cubic": {"max_delay": REALTIME_MAX_DELAY_US},
    "lif": {"dt": 1000},
}
#: Method label -> (registry name or "temporal", settings): every registry method that
#: streams (in its order, temporal funnelling after the causal region methods) with its
#: replay settings.
_STREAMING = [name for name, cls in METHODS.items()
              if cls.method is not None and cls.method.no_stream is None]
REALTIME_METHODS: dict[str, tuple[str, dict[str, Any]]] = {
    name: (name, REALTIME_SETTINGS.get(name, {}))
    for name in [*_STREAMING[:3], "temporal", *_STREAMING[3:]]
}


#: The floor's label: replayed before the methods at every rate and chunk size.
FLOOR = "floor"


#: Environment variables that set glibc's malloc (read once, when the process starts).
ALLOCATOR_VARIABLES = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_",
                       "MALLOC_MMAP_MAX_", "GLIBC_TUNABLES", "LD_PRELOAD")


def allocator_settings(environ: Mapping[str, str] | None = None) -> str:
    """The memory allocator settings this process runs under, in words (for the report).

    Example:
        >>> allocator_settings({})
        'glibc defaults (freed memory goes back to the system)'
        >>> allocator_settings({"MALLOC_TRIM_THRESHOLD_": "1073741824", "HOME": "/root"})
        'MALLOC_TRIM_THRESHOLD_=1073741824'
    """
    environ = os.environ if environ is None else environ
    named = [f"{name}={environ[name]}" for name in ALLOCATOR_VARIABLES if environ.get(name)]
    return ", ".join(named) if named else "glibc defaults (freed memory goes back to the system)"


def minor_faults() -> int:
    """Minor page faults of this process so far (0 where the platform does not count them)."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not on Unix
        return 0
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_minflt)


@dataclass
class ReplayResult:
    """One method replayed at one rate in chunks of one duration.

    Attributes:
        method: the method's label.
        rate: the replayed input rate (events per second).
        chunk_us: chunk duration in stream time (microseconds).
        chunks: number of timed chunks (the warm-up chunk excluded).
        events_in: input events of the timed chunks.
        events_out: output events of the whole replay (flush included).
        seconds: wall-clock seconds of each timed chunk.
        cpu_seconds: process CPU seconds of each timed chunk.
        chunk_events: input events of each timed chunk.
        faults: minor page faults (memory the process had given back and touched again)
            during each timed chunk.
        delays_us: output delay of every output event (only for lagging methods).
        note: why a method was skipped, else empty.
        algorithmic_delay_us: the method's own delay (its ``algorithmic_delay()``, in us).
    """

    method: str
    rate: float
    chunk_us: int
    chunks: int = 0
    events_in: int = 0
    events_out: int = 0
    seconds: list[float] = field(default_factory=list)
    cpu_seconds: list[float] = field(default_factory=list)
    chunk_events: list[int] = field(default_factory=list)
    faults: list[int] = field(default_factory=list)
    delays_us: list[float] = field(default_factory=list)
    note: str = ""
    algorithmic_delay_us: float = 0.0

    @property
    def median_s(self) -> float | None:
        """Median processing time of a chunk (seconds)."""
        return statistics.median(self.seconds) if self.seconds else None

    @property
    def p99_s(self) -> float | None:
        """99th percentile of the processing time of a chunk (seconds)."""
        return float(np.percentile(self.seconds, 99)) if self.seconds else None

    @property
    def p99_cpu_s(self) -> float | None:
        """99th percentile of the CPU time of a chunk (seconds)."""
        return float(np.percentile(self.cpu_seconds, 99)) if self.cpu_seconds else None

    @property
    def keeps_up(self) -> bool | None:
        """Whether the 99th percentile is below the chunk's duration."""
        p99 = self.p99_s
        return None if p99 is None else p99 < self.chunk_us * 1e-6

    @property
    def latency_budget_s(self) -> float | None:
        """Algorithmic delay + chunk duration + 99th percentile of the processing (seconds).

        ``None`` when nothing was timed or the method does not keep up (its queue, and so its
        latency, grows without bound).
        """
        p99 = self.p99_s
        if p99 is None or not self.keeps_up:
            return None
        return (self.algorithmic_delay_us + self.chunk_us) * 1e-6 + p99

    @property
    def sustained_rate(self) -> float | None:
        """Input rate (events/s) at which a chunk's 99th-percentile time reaches its duration.

        Chunk times are taken in proportion to their events.
        """
        p99 = self.p99_s
        if p99 is None or p99 <= 0:
            return None
        return self.rate * self.chunk_us * 1e-6 / p99

    def summary(self) -> dict[str, Any]:
        """The result with its statistics, for JSON."""
        out = asdict(self)
        for name in ("seconds", "cpu_seconds", "chunk_events", "faults"):
            out.pop(name)
        delays = out.pop("delays_us")
        out.update(median_s=self.median_s, p99_s=self.p99_s, p99_cpu_s=self.p99_cpu_s,
                   keeps_up=self.keeps_up, latency_budget_s=self.latency_budget_s,
                   sustained_rate=self.sustained_rate,
                   median_faults=statistics.median(self.faults) if self.faults else None)
        if delays:
            out["delay_us"] = {q: float(np.percentile(delays, p)) for q, p in
                               (("median", 50), ("p99", 99), ("max", 100))}
        return out


def retime(events: np.ndarray, rate: float | None) -> tuple[np.ndarray, float]:
    """The recording at ``rate`` events per second (``None``: its own rate), and that rate.

    Timestamps are compressed (or stretched) about the first one by the ratio of the rates,
    rounded down to microseconds, so the order and the relative timing stay.
    """
    t = events["t"].astype(np.int64)
    span_us = max(int(t[-1] - t[0]), 1)
    own = len(events) / (span_us * 1e-6)
    if rate is None:
        return events, own
    out = events.copy()
    out["t"] = t[0] + np.floor((t - t[0]) * (own / rate)).astype(np.int64)
    return out, rate


def chunk_bounds_us(t: np.ndarray, chunk_us: int) -> np.ndarray:
    """Start indices of the consecutive chunks of sorted timestamps ``t``.

    Chunk ``k`` is ``[t0 + k * chunk_us, t0 + (k + 1) * chunk_us)`` (it may be empty);
    ``len(t)`` ends the list.
    """
    if len(t) == 0:
        return np.zeros(1, dtype=np.int64)
    t0 = int(t[0])
    edges = t0 + chunk_us * np.arange(1, (int(t[-1]) - t0) // chunk_us + 1, dtype=np.int64)
    return np.concatenate([[0], np.searchsorted(t, edges, side="left"), [len(t)]])


def _transform(
    label: str, sensor_size: tuple[int, int, int], factor: int
) -> Streaming | RegionFloor:
    if label == FLOOR:
        return RegionFloor(sensor_size, factor)
    name, settings = REALTIME_METHODS[label]
    if name == "temporal":
        return Chain(TemporalFunnelling(sensor_size=sensor_size, **settings),
                     make_method("downsample", sensor_size, factor))
    return make_method(name, sensor_size, factor, **settings)


def replay(
    transform: Streaming | RegionFloor,
    events: np.ndarray,
    *,
    chunk_us: int,
    label: str = "",
    rate: float = 0.0,
    max_chunks: int | None = None,
    lagging: bool = False,
) -> ReplayResult:
    """Replay sorted ``events`` through ``transform.session()`` in chunks of ``chunk_us``.

    Args:
        transform: a transform with a session (or the floor).
        events: a Tonic structured array sorted by ``t`` (microseconds).
        chunk_us: chunk duration in stream time (microseconds, > 0).
        label: the method's name in the result.
        rate: the replayed rate, for the result.
        max_chunks: time at most this many chunks after the warm-up one (``None``: all).
        lagging: record the output delay of every output event a chunk returns.

    Returns:
        The :class:`ReplayResult`; the first chunk warms up and the stream's last chunk is
        cut short by its end: both are processed but not timed.

    Example:
        >>> from evdown_torch import Downsample
        >>> from evdown_torch.events import DVS_DTYPE
        >>> ev = np.zeros(6, dtype=DVS_DTYPE)
        >>> ev["t"] = [0, 500, 1000, 1500, 2500, 4000]
        >>> r = replay(Downsample((4, 4, 2), factor=2), ev, chunk_us=1000)
        >>> r.chunks, r.events_in, r.events_out, len(r.seconds)
        (3, 3, 6, 3)
    """
    chunk_us = check_positive_int("chunk_us", chunk_us)
    result = ReplayResult(label or type(transform).__name__, rate, chunk_us,
                          algorithmic_delay_us=transform.algorithmic_delay())
    session = transform.session()
    bounds = chunk_bounds_us(events["t"], chunk_us)
    t0 = int(events["t"][0]) if len(events) else 0
    last = len(bounds) - 1 if max_chunks is None else min(len(bounds) - 1, max_chunks + 1)
    for k in range(last):
        chunk = events[bounds[k]:bounds[k + 1]]
        faults = minor_faults()
        start, start_cpu = time.perf_counter(), time.process_time()
        out = session(chunk)
        elapsed, cpu = time.perf_counter() - start, time.process_time() - start_cpu
        if 0 < k < len(bounds) - 2:  # neither the warm-up nor the stream's last chunk
            result.faults.append(minor_faults() - faults)
            result.seconds.append(elapsed)
            result.cpu_seconds.append(cpu)
            result.chunk_events.append(len(chunk))
            result.events_in += len(chunk)
        result.events_out += len(out)
        if lagging and len(out):
            emitted_at = t0 + (k + 1) * chunk_us
            emitted = cast(np.ndarray, out)  # a structured array in, one out
            result.delays_us.extend((emitted_at - emitted["t"]).astype(float).tolist())
    # What the flush returns is decided by the end of the (replayed part of the) stream, not
    # by the delay: its events are counted but have no delay.
    result.events_out += len(session.flush())
    result.chunks = len(result.seconds)
    return result


def realtime_benchmark(
    events: np.ndarray,
    sensor_size: tuple[int, int, int],
    *,
    factor: int = 4,
    methods: Sequence[str] | None = None,
    chunks_us: Sequence[int] = REALTIME_CHUNKS_US,
    rates: Sequence[float | None] = (None, REALTIME_RATE),
    max_chunks: int = 50,
) -> list[ReplayResult]:
    """Replay a recording through every method at every rate and chunk size (one thread).

    Args:
        events: the recording, a Tonic structured array sorted by ``t`` (microseconds).
        sensor_size: its ``(W, H, P)``.
        factor: the downscaling factor.
        methods: labels of :data:`REALTIME_METHODS` (default: all); the :data:`FLOOR` is
            replayed first in any case.
        chunks_us: chunk durations (microseconds).
        rates: replayed rates in events per second; ``None`` is the recording's own.
        max_chunks: timed chunks per replay at most.

    Returns:
        One :class:`ReplayResult` per method (the floor's first), rate and chunk size.
    """
    with torch_threads(1):
        return _replay_all(events, sensor_size, factor, methods, chunks_us, rates, max_chunks)


def _replay_all(events: np.ndarray, sensor_size: tuple[int, int, int], factor: int,
                methods: Sequence[str] | None, chunks_us: Sequence[int],
                rates: Sequence[float | None], max_chunks: int) -> list[ReplayResult]:
    results = []
    for rate in rates:
        stream, actual = retime(events, rate)
        for chunk_us in chunks_us:
            for label in [FLOOR, *(methods or REALTIME_METHODS)]:
                if label != FLOOR and label not in REALTIME_METHODS:
                    raise ValueError(f"unknown realtime method {label!r}; expected one of "
                                     f"{sorted(REALTIME_METHODS)}")
                transform = _transform(label, sensor_size, factor)
                try:
                    session = transform.session()
                except (NotImplementedError, ValueError) as error:
                    results.append(ReplayResult(label, actual, chunk_us, note=str(error)))
                    continue
                if not hasattr(session, "flush"):
                    results.append(ReplayResult(label, actual, chunk_us, note=(
                        f"{type(session).__name__} is not the common session (no flush)")))
                    continue
                lagging = label != FLOOR and "max_delay" in REALTIME_METHODS[label][1]
                results.append(replay(transform, stream, chunk_us=chunk_us, label=label,
                                      rate=actual, max_chunks=max_chunks, lagging=lagging))
    return results


def _ms(seconds: float | None) -> str:
    return "–" if seconds is None else f"{seconds * 1e3:.3g}"


#: The peer of the "x EventCount" column: the cheapest method that also cuts the rate.
PEER = "event_count"


def _ratio(result: ReplayResult, to: dict[tuple[float, int], float | None]) -> str:
    """``result``'s sustained rate over the one in ``to`` at its rate and chunk size."""
    sustained, other = result.sustained_rate, to.get((result.rate, result.chunk_us))
    return "–" if sustained is None or not other else f"{sustained / other:.3g}"


def realtime_markdown(results: Sequence[ReplayResult]) -> str:
    """The results as a Markdown table (times in ms, rates in M events/s, delays in µs).

    With :data:`PEER` (EventCount) among them, the column "x EventCount" gives each method's
    sustained rate over EventCount's at the same input rate and chunk size, in the same run:
    a ratio that the machine's speed and load move far less than the rates themselves; with
    the :data:`FLOOR`, the column "x floor" gives it over the floor's. The last column is the
    latency budget (:attr:`ReplayResult.latency_budget_s`): algorithmic delay + chunk + p99,
    or "falls behind" where the p99 exceeds the chunk.
    """
    peer, floor = ({(r.rate, r.chunk_us): r.sustained_rate for r in results
                    if r.method == label and not r.note} for label in (PEER, FLOOR))
    lines = ["| method | input rate (M ev/s) | chunk (ms) | chunks | median (ms) | p99 (ms) | "
             "p99 CPU (ms) | keeps up | sustains (M ev/s) | x EventCount | x floor | "
             "delay median / p99 / max (µs) | algorithmic delay (ms) | "
             "latency budget (ms): delay + chunk + p99 |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        if r.note:
            lines.append(f"| {r.method} | {r.rate / 1e6:.3g} | {r.chunk_us / 1e3:g} | – | – | – "
                         f"| – | – | – | – | – | {r.note.split(';')[0]} | – | – |")
            continue
        s = r.summary()
        delay = s.get("delay_us")
        delay_text = ("–" if delay is None else
                      f"{delay['median']:.0f} / {delay['p99']:.0f} / {delay['max']:.0f}")
        sustained = r.sustained_rate
        lines.append(
            f"| {r.method} | {r.rate / 1e6:.3g} | {r.chunk_us / 1e3:g} | {r.chunks} "
            f"| {_ms(r.median_s)} | {_ms(r.p99_s)} | {_ms(r.p99_cpu_s)} "
            f"| {'–' if r.keeps_up is None else 'yes' if r.keeps_up else 'no'} "
            f"| {'–' if sustained is None else f'{sustained / 1e6:.3g}'} | {_ratio(r, peer)} "
            f"| {_ratio(r, floor)} | {delay_text} | {_ms(r.algorithmic_delay_us * 1e-6)} "
            f"| {_latency(r)} |")
    return "\n".join(lines) + "\n"


def _latency(result: ReplayResult) -> str:
    """The latency budget in ms, "falls behind" where the method does not keep up."""
    if result.keeps_up is False:
        return "falls behind"
    return _ms(result.latency_budget_s)


def write_realtime_report(
    results: Sequence[ReplayResult], out_dir: str | Path, *, header: str = ""
) -> list[Path]:
    """Write ``realtime.md``, ``realtime.json`` and (with matplotlib) ``realtime.png``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "realtime.md", out / "realtime.json"]
    written[0].write_text(header + realtime_markdown(results))
    written[1].write_text(json.dumps([r.summary() for r in results], indent=1))
    try:
        from matplotlib.figure import Figure
    except ImportError:
        return written
    measured = [r for r in results if r.seconds]
    if not measured:
        return written
    fig = Figure(figsize=(10, 4.5), layout="constrained")
    ax = fig.subplots()
    keys = sorted({(r.rate, r.chunk_us) for r in measured})
    labels = list(dict.fromkeys(r.method for r in measured))
    width = 0.8 / len(keys)
    for i, (rate, chunk_us) in enumerate(keys):
        rows = {r.method: r for r in measured if (r.rate, r.chunk_us) == (rate, chunk_us)}
        xs = [j + i * width for j, m in enumerate(labels) if m in rows]
        ys = [(rows[m].sustained_rate or 0.0) / 1e6 for m in labels if m in rows]
        ax.bar(xs, ys, width, label=f"{rate / 1e6:.3g} M ev/s in {chunk_us / 1e3:g} ms chunks")
    ax.axhline(REALTIME_RATE / 1e6, color="k", linestyle="--", linewidth=1, label="25 M ev/s")
    ax.set_yscale("log")
    ax.set_xticks([j + 0.4 - width / 2 for j in range(len(labels))], labels)
    ax.set_ylabel("sustained input rate (M events/s, p99)")
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    written.append(out / "realtime.png")
    fig.savefig(written[-1], dpi=110)
    return written
