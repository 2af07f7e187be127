"""One benchmark run: its plan (sizes), the measurements and :func:`run_benchmark`."""

from __future__ import annotations

import math
import os
import platform
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from tqdm import tqdm

from evdown_torch.bench.inputs import (
    EVENTS_SWEEP_RATE,
    LARGE_RATE,
    BenchInput,
    dvs_like_stream,
    gesture_stream,
    read_nmnist,
    stream_duration_s,
    with_pauses,
)
from evdown_torch.bench.lineup import (
    PEER_MEMORY_BUDGET,
    Candidate,
    candidate_job,
    candidates,
    tonic_available,
)
from evdown_torch.bench.measure import MemoryJob, measure_memory, time_call
from evdown_torch.checks import check_positive_int, check_sensor_size
from evdown_torch.io import read_microseconds
from evdown_torch.time_units import timing_checked_by_caller

__all__ = [
    "BenchResults",
    "Measurement",
    "Plan",
    "log",
    "machine_description",
    "make_plan",
    "run_benchmark",
    "stage_bar",
]

def log(message: str) -> None:
    """A progress line on stderr (above the progress bar, if one is shown)."""
    tqdm.write(f"[evdown bench] {message}", file=sys.stderr)
    sys.stderr.flush()


def stage_bar(label: str, total: int) -> tqdm:
    """The progress bar of one stage of the run: ``total`` measurements (on a terminal only)."""
    return tqdm(total=total, desc=f"evdown bench: {label}", unit="measurement", leave=False,
                file=sys.stderr, disable=not sys.stderr.isatty(), dynamic_ncols=True)

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
        self.bar: tqdm | None = None  # the current stage's progress bar

    def add_input(self, name: str, events: np.ndarray, sensor_size: tuple[int, int, int],
                  source: str) -> BenchInput:
        path = self.tmp / f"{name}.npy"
        np.save(path, events)
        inp = BenchInput(name, check_sensor_size(sensor_size), len(events),
                         stream_duration_s(events),
                         source, str(path))
        self.inputs.append(inp)
        return inp

    def measure(self, section: str, inp: BenchInput, events: np.ndarray,
                factor: int | tuple[int, int], repeats: int, x: float | None = None) -> None:
        for cand in self.cands:
            if self.bar is not None:
                self.bar.update()
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
            rate = cast(float, m.rate)  # timed: it has a rate
            log(f"{section} {inp.name} f={factor} {cand.name}: {rate / 1e6:.2f} M events/s")
            if self.memory:
                self.jobs.append((m, candidate_job(cand.name, inp.path, inp.sensor_size, factor)))

    def measure_memory(self) -> None:
        if not self.jobs:
            return
        log(f"peak memory: {len(self.jobs)} measurements in a fresh process")
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
    nmnist: str | Path | None = None,
    time_unit: str | None = None,
    columns: Sequence[str] | str | None = None,
) -> BenchResults:
    """Run the benchmark: the method table, the scaling sweeps and the peak memory.

    Args:
        short: the short mode (small inputs, two points per sweep; under 2 minutes).
        inputs: extra event files to add to the method table (any format
            :func:`evdown_torch.io.read_events` reads).
        sensor_size: the sensor of those files that do not record one (default: guessed
            from the largest coordinates, with a warning).
        events: cap on every stream's number of events (quick checks).
        repeats: timed calls per measurement of the method table (default 5).
        methods: a subset of method and peer names (default: all of them).
        scaling: run the scaling sweeps.
        memory: measure peak memory.
        seed: seed of the synthetic streams.
        nmnist: an N-MNIST ``.bin`` recording (34x34) to add to the method table as
            ``nmnist`` (``benchmarks/bench_all.py`` adds the repository's sample).
        time_unit: the unit of ``t`` in input files that state none (converted to
            microseconds; :func:`evdown_torch.io.read_microseconds`).
        columns: the column order of ``(N, 4)`` ``.npy`` inputs, e.g. ``"t,x,y,p"``.

    Returns:
        The results, for :func:`write_report`.
    """
    plan = make_plan(short, events, repeats)
    if nmnist is not None and not Path(nmnist).is_file():
        raise ValueError(f"N-MNIST file {str(nmnist)!r} does not exist")
    if sensor_size is not None:
        sensor_size = check_sensor_size(sensor_size)
    extra = [(Path(p), read_microseconds(p, sensor_size=sensor_size, time_unit=time_unit,
                                         **({} if columns is None else {"columns": columns})))
             for p in inputs]
    cands = candidates(methods)
    notes = []
    if not tonic_available():
        notes.append("Tonic is not installed: the peers are not measured.")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    start = time.perf_counter()
    run = None
    try:
        # The inputs' timing was checked as they were read; the timed transforms keep quiet.
        with timing_checked_by_caller(), tempfile.TemporaryDirectory(prefix="evdown-bench-") \
                as tmp:
            run = _Runner(plan, cands, memory, Path(tmp))
            tables = (1 + (nmnist is not None) + len(extra)) * len(plan.factors) + 1
            run.bar = stage_bar("method tables", tables * len(cands))
            events_, source = _headline_stream(plan, seed)
            inp = run.add_input("gesture", events_, (128, 128, 2), source)
            for factor in plan.factors:
                run.measure("methods", inp, events_, factor, plan.repeats)
            if nmnist is not None:
                events_ = read_nmnist(nmnist)
                inp = run.add_input("nmnist", events_, (34, 34, 2),
                                    f"real N-MNIST recording ({Path(nmnist).name})")
                for factor in plan.factors:
                    run.measure("methods", inp, events_, factor, plan.repeats)
            for path, recording in extra:
                events_ = recording.events
                inp = run.add_input(path.stem, events_, recording.sensor_size, f"file {path}")
                for factor in plan.factors:
                    run.measure("methods", inp, events_, factor, plan.repeats)
            duration = max(int(plan.large_events / LARGE_RATE * 1e6), 1)
            events_ = dvs_like_stream(plan.large_events, (1280, 720, 2), duration_us=duration,
                                      seed=seed + 1, num_objects=12)
            inp = run.add_input("large", events_, (1280, 720, 2),
                                f"dvs_like_stream, 12 bars, {duration / 1e6:.2f} s")
            run.measure("methods", inp, events_, 4, plan.repeats)
            run.bar.close()
            del events_
            if scaling:
                points = (len(plan.events_sweep) + len(plan.sensor_sweep)
                          + len(plan.duration_sweep_s))
                run.bar = stage_bar("scaling sweeps", points * len(cands))
                _sweeps(run, plan, seed)
                run.bar.close()
            run.bar = None
            run.measure_memory()
    finally:
        if run is not None and run.bar is not None:
            run.bar.close()
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
