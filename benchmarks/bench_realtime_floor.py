"""What the live replay's speed goals leave each method, against the work it cannot skip.

Issue 29 asks, in the live replay (``evdown bench --realtime``: a synthetic gesture recording
retimed to 25 M events/s, 10 ms chunks, factor 4, one thread), for PhotocurrentPooling to
sustain 0.85x EventCount's rate, LinearEstimation 0.35x and CubicEstimation 0.17x. A chunk
may then cost at most EventCount's chunk over the goal: 1.18x, 2.86x and 5.9x of it.

This script replays the same chunks through each method's session, in one process, and
measures the CPU time (``time.thread_time``) of each chunk and of named parts of the kernel
that the method's output cannot do without in its present design ("floor" parts):

* PhotocurrentPooling: its stable sorts (events to region order and crossings back to time
  order, as EventCount's), each event's pixel level before it (``grouped_levels``), and the
  reference rule (``rule_crossings``, as EventCount's).
* LinearEstimation and CubicEstimation: grouping the window by region (``region_chunks``)
  and each pixel's knots and each region's breakpoints (``pixel_knots``).

For each method it prints the chunks' total CPU time over EventCount's (the cost ratio the
goal bounds), the floor parts' total over EventCount's, and how much cheaper the rest of the
kernel (everything but the floor parts) would have to get for the goal. Where the floor
alone is above the goal's bound, no change to the rest reaches the goal: the floor parts
themselves must get cheaper. The parts are measured by wrapping the functions where the
kernels look them up, so the wrapped names are part of this script's contract with the
package (a test runs it on a tiny replay).

The parts are those of the eager torch kernels, so every replay here runs under
:func:`evdown_torch.eager_kernels` (EventCount's too, so that the ratios compare eager with
eager); the compiled loops' speed is measured by ``evdown bench --realtime`` against its own
floor.

Run: ``python benchmarks/bench_realtime_floor.py [--events 13000000] [--chunks 50] [--runs 3]``
(the defaults are the full replay's recording and timed chunks; about a minute).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
import torch

from evdown_torch import eager_kernels
from evdown_torch.bench.inputs import gesture_stream
from evdown_torch.bench.realtime import (
    REALTIME_METHODS,
    REALTIME_RATE,
    chunk_bounds_us,
    retime,
)
from evdown_torch.transforms.functional.estimation import driver
from evdown_torch.transforms.functional.photocurrent import events_mode
from evdown_torch.transforms.registry import make_method

SENSOR = (128, 128, 2)

#: The goals of issue 29, item 2 and item 1: sustained rate over EventCount's.
GOALS = {"photocurrent": 0.85, "linear": 0.35, "cubic": 0.17}

#: The floor parts of each method: (module, function name, is a generator).
FLOOR: dict[str, tuple[tuple[ModuleType, str, bool], ...]] = {
    "photocurrent": ((events_mode, "stable_sort_small", False),
                     (events_mode, "grouped_levels", False),
                     (events_mode, "rule_crossings", False)),
    "linear": ((driver, "region_chunks", True), (driver, "pixel_knots", False)),
    "cubic": ((driver, "region_chunks", True), (driver, "pixel_knots", False)),
}


@dataclass
class Replay:
    """One method's replay: CPU seconds of the timed chunks, whole and per floor part."""

    method: str
    chunks: list[float]
    parts: dict[str, float]

    @property
    def total(self) -> float:
        return sum(self.chunks)


def _timed(function: Callable[..., Any], name: str, spent: dict[str, float],
           generator: bool) -> Callable[..., Any]:
    if not generator:
        def call(*args: Any, **kwargs: Any) -> Any:
            start = time.thread_time()
            try:
                return function(*args, **kwargs)
            finally:
                spent[name] += time.thread_time() - start
        return call

    def walk(*args: Any, **kwargs: Any) -> Iterator[Any]:
        items = function(*args, **kwargs)
        while True:
            start = time.thread_time()
            try:
                item = next(items)
            except StopIteration:
                return
            finally:
                spent[name] += time.thread_time() - start
            yield item
    return walk


@contextmanager
def measured(parts: tuple[tuple[ModuleType, str, bool], ...],
             spent: dict[str, float]) -> Iterator[None]:
    """Time ``parts`` (module attributes) into ``spent`` while the block runs."""
    saved = [(module, name, getattr(module, name)) for module, name, _ in parts]
    for module, name, generator in parts:
        spent.setdefault(name, 0.0)
        setattr(module, name, _timed(getattr(module, name), name, spent, generator))
    try:
        yield
    finally:
        for module, name, function in saved:
            setattr(module, name, function)


def replay(method: str, stream: np.ndarray, bounds: np.ndarray, chunks: int) -> Replay:
    """Chunk 0 warms up; chunks ``1 .. chunks`` are timed (the stream's last is never)."""
    name, settings = REALTIME_METHODS[method]
    session = make_method(name, SENSOR, 4, **settings).session()
    spent: dict[str, float] = {}
    times = []
    last = min(chunks, len(bounds) - 3)
    with eager_kernels():
        session(stream[bounds[0]:bounds[1]])
        with measured(FLOOR.get(method, ()), spent):
            for k in range(1, last + 1):
                start = time.thread_time()
                session(stream[bounds[k]:bounds[k + 1]])
                times.append(time.thread_time() - start)
    return Replay(method, times, spent)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=13_000_000)
    parser.add_argument("--chunks", type=int, default=50, help="timed 10 ms chunks")
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    stream, _ = retime(gesture_stream(args.events, sensor_size=SENSOR), REALTIME_RATE)
    bounds = chunk_bounds_us(stream["t"], 10_000)
    if len(bounds) < 4:
        parser.error("the replay needs at least two 10 ms chunks: give more --events")
    rows: dict[str, list[tuple[float, float]]] = {method: [] for method in GOALS}
    base_ms: list[float] = []
    for run in range(args.runs):
        base = replay("event_count", stream, bounds, args.chunks)
        base_ms.append(1e3 * statistics.median(base.chunks))
        for method in GOALS:
            result = replay(method, stream, bounds, args.chunks)
            rows[method].append((result.total / base.total,
                                 sum(result.parts.values()) / base.total))
            parts = ", ".join(f"{name} {1e3 * s / len(result.chunks):.2f}"
                              for name, s in result.parts.items())
            print(f"run {run + 1} {method}: {len(result.chunks)} chunks, median "
                  f"{1e3 * statistics.median(result.chunks):.2f} ms; floor ms/chunk: {parts}")
    print(f"\nEventCount's median chunk: {statistics.median(base_ms):.2f} ms CPU "
          f"({len(bounds) - 1} chunks of 10 ms, medians over {args.runs} runs below)\n")
    print("| method | goal | bound | chunk cost | floor parts | the rest | rest allowed "
          "| rest must be |")
    print("|---|---|---|---|---|---|---|---|")
    for method, goal in GOALS.items():
        cost = statistics.median(r[0] for r in rows[method])
        floor = statistics.median(r[1] for r in rows[method])
        room = 1 / goal - floor
        must = f"{(cost - floor) / room:.1f}x cheaper" if room > 0 else "impossible"
        print(f"| {method} | {goal}x | {1 / goal:.2f} | {cost:.2f} | {floor:.2f} "
              f"| {cost - floor:.2f} | {max(room, 0):.2f} | {must} |")
    print("\n(Every figure but the goal and the last column: CPU time over EventCount's on the "
          "same chunks.)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
