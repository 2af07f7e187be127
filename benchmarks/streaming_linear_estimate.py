"""LinearEstimation's compiled bounded-delay session in the live replay, beside its loops alone.

Issue 38's goals 1 and 2 ask LinearEstimation with ``max_delay`` to keep up with the live
replay (the synthetic gesture recording retimed to 25 M events/s, 10 ms chunks, factor 4, one
thread), at 0.08 of the floor's rate or more. On the CPU with int64 timestamps the package's
session steps each chunk through the ramps
(:mod:`evdown_torch.transforms.functional.compiled.linear_ramps`): each event's ramp goes into
one of two time-ordered rings (its end; its start at ``t - D`` unless it starts at the pixel's
previous knot), and a merge of the rings advances each output region lazily, in fixed-point
integers, deciding what those integers cannot (a *doubt*: a value near a level, a crossing near a
half tick) on its value less the error it tracks. Its state between chunks is the package's
``WindowState``, made from the ramps' session each chunk
(:mod:`~evdown_torch.transforms.functional.compiled.linear_ramps_state`).

This script times, on the same chunks and in the same run, the floor, the package's session,
the package's windowed session (the ramps switched off: what it was before them) and the ramps'
session alone (no state made: what the conversion costs), and counts the events
in one output and not the other (pairing those one tick apart) and the doubts decided on the
corrected value. The eager twin (:func:`~benchmarks.streaming_linear_twin.design_whole`,
vectorised torch, the whole stream at once) must give the ramps' events whatever the chunks.

Run: ``python benchmarks/streaming_linear_estimate.py [--events 13000000] [--chunks 50]``.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script

from benchmarks.streaming_linear_twin import (  # noqa: E402
    FACTOR,
    SENSOR,
    THRESHOLD,
    RampArrays,
    design_whole,
)
from evdown_torch.bench.estimates import estimate_replay  # noqa: E402
from evdown_torch.bench.floor import RegionFloor  # noqa: E402
from evdown_torch.bench.realtime import REALTIME_MAX_DELAY_US  # noqa: E402
from evdown_torch.transforms.functional.compiled import numba_available  # noqa: E402
from evdown_torch.transforms.registry import make_method  # noqa: E402


class Windowed:
    """A session whose linear steps take the windowed session (the ramps switched off)."""

    def __init__(self, session: Callable[[np.ndarray], np.ndarray]) -> None:
        self.session = session

    def __call__(self, chunk: np.ndarray) -> np.ndarray:
        from evdown_torch.transforms.functional.compiled import linear_stream

        with mock.patch.object(linear_stream, "ramps_step", lambda *_: None):
            return self.session(chunk)


def main(argv: list[str] | None = None) -> int:
    replay = estimate_replay(argv, __doc__, compiled=numba_available(), sensor_size=SENSOR)
    if replay is None:
        return 2
    stream, bounds, last = replay
    chunks = [stream[int(bounds[k]):int(bounds[k + 1])] for k in range(last + 1)]
    a, b = THRESHOLD
    t_start, most = int(stream["t"][0]), max(len(c) for c in chunks)
    sessions = {
        "floor": RegionFloor(SENSOR, FACTOR).session(),
        "package": make_method("linear", SENSOR, FACTOR, threshold=a / b,
                               max_delay=REALTIME_MAX_DELAY_US).session(),
        "package, windowed (ramps off)": Windowed(
            make_method("linear", SENSOR, FACTOR, threshold=a / b,
                        max_delay=REALTIME_MAX_DELAY_US).session()),
        "ramps alone": RampArrays(t_start, most),
    }
    seconds: dict[str, list[float]] = {name: [] for name in sessions}
    outputs: dict[str, list[np.ndarray]] = {name: [] for name in sessions}
    for k, chunk in enumerate(chunks):  # chunk 0 warms up (and compiles)
        for name, session in sessions.items():
            start = time.perf_counter()
            made = session(chunk)
            if k:
                seconds[name].append(time.perf_counter() - start)
            outputs[name].append(made)
    n_events = int(bounds[last + 1] - bounds[1])
    floor_total = sum(seconds["floor"])
    floor_p99 = float(np.quantile(seconds["floor"], 0.99))
    print(f"{last} chunks of 10 ms, {n_events:,} events (25 M/s on average), "
          f"max_delay {REALTIME_MAX_DELAY_US} us, threshold {a / b}; wall time, one thread\n")
    print("| session | median chunk (ms) | p99 chunk (ms) | ns per event | x floor (p99s, as "
          "the replay) | x floor (total times) | output events |")
    print("|---|---|---|---|---|---|---|")
    for name, times in seconds.items():
        p99 = float(np.quantile(times, 0.99))
        made = sum(len(o) for o in outputs[name])
        print(f"| {name} | {1e3 * statistics.median(times):.2f} | {1e3 * p99:.2f} "
              f"| {1e9 * sum(times) / n_events:.1f} | {floor_p99 / p99:.4f} "
              f"| {floor_total / sum(times):.4f} | {made:,} |")
    horizon = min(int(np.concatenate(outputs[n])["t"].max()) for n in ("package", "ramps alone"))

    def keys(name: str, before: int) -> Counter:
        out = np.concatenate(outputs[name])
        out = out[out["t"] < before]
        return Counter(zip(out["x"].tolist(), out["y"].tolist(), out["t"].tolist(),
                           out["p"].tolist(), strict=True))

    # Events before the cut; their partners a tick away may lie on it.
    package, design = keys("package", horizon - 1), keys("ramps alone", horizon - 1)
    only_package, only_design = package - design, design - package
    spare = keys("ramps alone", horizon) - keys("package", horizon)
    paired = 0
    for (x, y, t, p), count in only_package.items():
        for shifted in ((x, y, t - 1, p), (x, y, t + 1, p)):
            matched = min(count, spare[shifted])
            spare[shifted] -= matched
            count -= matched
            paired += matched
    print(f"\nbefore t = {horizon - 1}: package {sum(package.values()):,} events, ramps alone "
          f"{sum(design.values()):,}; in one and not the other: "
          f"{sum(only_package.values()):,} and {sum(only_design.values()):,}, of which "
          f"{paired:,} pairs one tick apart")
    counts = sessions["ramps alone"].counts
    print(f"doubts decided on the corrected value (the integers within their error bound of "
          f"a level, of a half tick): {int(counts[0]):,} and {int(counts[1]):,}, "
          f"{1e6 * int(counts.sum()) / n_events:.1f} per million input events")
    for (x, y, t, p), count in sorted((only_package + only_design).items())[:10]:
        side = "package" if (x, y, t, p) in only_package else "ramps alone"
        print(f"  only in the {side}'s output: x {x}, y {y}, t {t}, p {p} (x{count})")
    package_out = np.concatenate(outputs["package"])
    windowed_out = np.concatenate(outputs["package, windowed (ramps off)"])
    same_windowed = np.array_equal(package_out, windowed_out)
    print(f"the package's windowed session: {len(windowed_out):,} events, "
          f"{'the same as' if same_windowed else 'NOT the same as'} its session through the "
          f"ramps ({len(package_out):,}), in the same order")
    # The eager twin on everything the session read, at once, against the session's chunks.
    cut = sessions["ramps alone"].horizon
    start = time.perf_counter()
    whole = design_whole(stream[: int(bounds[last + 1])], cut)
    seconds_whole = time.perf_counter() - start
    chunked = np.concatenate(outputs["ramps alone"])
    chunked = np.sort(chunked[chunked["t"] < cut], order=["t", "x", "y", "p"])
    same = np.array_equal(chunked, np.sort(whole, order=["t", "x", "y", "p"]))
    print(f"eager twin, the {int(bounds[last + 1]):,} events at once (torch, one thread): "
          f"{len(whole):,} events before t = {cut}, {'the same as' if same else 'NOT the same as'}"
          f" the session's in {last + 1} chunks; {seconds_whole:.1f} s "
          f"({1e9 * seconds_whole / int(bounds[last + 1]):.0f} ns per input event)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
