"""What a streaming LinearEstimation loop would cost in the live replay: an estimate for a design.

Issue 38's goals 1 and 2 ask LinearEstimation with ``max_delay`` to keep up with the live
replay (the synthetic gesture recording retimed to 25 M events/s, 10 ms chunks, factor 4, one
thread), at 0.08 of the floor's rate or more. The package's compiled session solves a *window*
of knot events each chunk with the batch driver's arithmetic (every float as the eager kernel
computes it) and keeps the knot events the future needs: it groups and sorts every chunk's
events by region and by pixel, and it reaches about 0.04 of the floor (docs/benchmarks.md).
This script measures, on the same chunks and in the same run as the package's session and
the floor, a design that needs neither a window nor a sort: two passes over each chunk.

The design (:mod:`benchmarks.streaming_linear_loops`): each event's ramp goes into one of two
time-ordered rings (its end; its start at ``t - D`` unless it starts at the pixel's previous
knot), and a merge of the rings advances each output region lazily, in fixed-point integers
(exact at every integer time, within ``A * D / 2`` units of the exact polyline with ``A``
ramps active). Where those integers cannot decide what the package decides (a value near a
level, a crossing near a half tick: a *doubt*), the sweep applies the package's rules to its
value less the error it tracks (each ramp's slope rounding is known).

The script times the design beside the package's session and the floor, counts the events in
one output and not the other (pairing those one tick apart), and the doubts decided on the
corrected value. Its eager twin (:func:`~benchmarks.streaming_linear_twin.design_whole`, vectorised
torch, the whole stream at once) must give the session's events whatever the chunks.

A fourth session runs the design with the package's own state between chunks
(:class:`~benchmarks.streaming_linear_state.ThroughState`: each chunk, the package's
``WindowState`` made from the design's session and a session made again from it alone), what
a compiled path sharing one state object with the eager path would pay; its events must be
the design's.

So the figures price a design; they are no implementation (integer timestamps only, rings
sized from the largest chunk, with an error, not a larger ring, when they fill; the twin
unoptimised). The script times the replay's settings; the loops and
the twin take any sensor, factor, threshold and ``max_delay`` (``Settings``).

Run: ``python benchmarks/streaming_linear_estimate.py [--events 13000000] [--chunks 50]``.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script

from benchmarks.streaming_linear_loops import (  # noqa: E402
    FACTOR,
    SENSOR,
    THRESHOLD,
    StreamingLinear,
    compile_loops,
    numba,
)
from benchmarks.streaming_linear_state import ThroughState, compile_state_loops  # noqa: E402
from benchmarks.streaming_linear_twin import design_whole  # noqa: E402
from evdown_torch.bench.estimates import estimate_replay  # noqa: E402
from evdown_torch.bench.floor import RegionFloor  # noqa: E402
from evdown_torch.bench.realtime import REALTIME_MAX_DELAY_US  # noqa: E402
from evdown_torch.transforms.registry import make_method  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    replay = estimate_replay(argv, __doc__, compiled=numba is not None, sensor_size=SENSOR)
    if replay is None:
        return 2
    stream, bounds, last = replay
    chunks = [stream[int(bounds[k]):int(bounds[k + 1])] for k in range(last + 1)]
    a, b = THRESHOLD
    compiled, t_start, most = compile_loops(), int(stream["t"][0]), max(len(c) for c in chunks)
    design = StreamingLinear(compiled, t_start, most)
    sessions = {
        "floor": RegionFloor(SENSOR, FACTOR).session(),
        "package": make_method("linear", SENSOR, FACTOR, threshold=a / b,
                               max_delay=REALTIME_MAX_DELAY_US).session(),
        "design": design,
        "design, the package's state between chunks": ThroughState(
            compiled, compile_state_loops(), design.settings, t_start, most),
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
    horizon = min(int(np.concatenate(outputs[n])["t"].max()) for n in ("package", "design"))

    def keys(name: str, before: int) -> Counter:
        out = np.concatenate(outputs[name])
        out = out[out["t"] < before]
        return Counter(zip(out["x"].tolist(), out["y"].tolist(), out["t"].tolist(),
                           out["p"].tolist(), strict=True))

    # Events before the cut; their partners a tick away may lie on it.
    package, design = keys("package", horizon - 1), keys("design", horizon - 1)
    only_package, only_design = package - design, design - package
    spare = keys("design", horizon) - keys("package", horizon)
    paired = 0
    for (x, y, t, p), count in only_package.items():
        for shifted in ((x, y, t - 1, p), (x, y, t + 1, p)):
            matched = min(count, spare[shifted])
            spare[shifted] -= matched
            count -= matched
            paired += matched
    print(f"\nbefore t = {horizon - 1}: package {sum(package.values()):,} events, design "
          f"{sum(design.values()):,}; in one and not the other: "
          f"{sum(only_package.values()):,} and {sum(only_design.values()):,}, of which "
          f"{paired:,} pairs one tick apart")
    counts = sessions["design"].counts
    print(f"doubts decided on the corrected value (the integers within their error bound of "
          f"a level, of a half tick): {int(counts[0]):,} and {int(counts[1]):,}, "
          f"{1e6 * int(counts.sum()) / n_events:.1f} per million input events")
    for (x, y, t, p), count in sorted((only_package + only_design).items())[:10]:
        side = "package" if (x, y, t, p) in only_package else "design"
        print(f"  only in the {side}'s output: x {x}, y {y}, t {t}, p {p} (x{count})")
    # Both return only events before their (equal) horizons.
    through = np.concatenate(outputs["design, the package's state between chunks"])
    design_out = np.concatenate(outputs["design"])
    same_through = np.array_equal(np.sort(through, order=["t", "x", "y", "p"]),
                                  np.sort(design_out, order=["t", "x", "y", "p"]))
    print(f"the design through the package's state: {len(through):,} events, "
          f"{'the same as' if same_through else 'NOT the same as'} the design's "
          f"{len(design_out):,}")
    # The eager twin on everything the session read, at once, against the session's chunks.
    cut = sessions["design"].horizon
    start = time.perf_counter()
    whole = design_whole(stream[: int(bounds[last + 1])], cut)
    seconds_whole = time.perf_counter() - start
    chunked = np.concatenate(outputs["design"])
    chunked = np.sort(chunked[chunked["t"] < cut], order=["t", "x", "y", "p"])
    same = np.array_equal(chunked, np.sort(whole, order=["t", "x", "y", "p"]))
    print(f"eager twin, the {int(bounds[last + 1]):,} events at once (torch, one thread): "
          f"{len(whole):,} events before t = {cut}, {'the same as' if same else 'NOT the same as'}"
          f" the session's in {last + 1} chunks; {seconds_whole:.1f} s "
          f"({1e9 * seconds_whole / int(bounds[last + 1]):.0f} ns per input event)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
