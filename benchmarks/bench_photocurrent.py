"""PhotocurrentPooling speed and memory (issue 14).

1. Speed, events mode against EventCount in the same run: on the harness's DVS-like streams
   (128x128 and 1280x720, ``--events`` events each, factors 2 and 4), one torch thread, each
   method timed alternately ``--repeats`` times (median of the wall-clock and CPU times);
   the ratio of throughputs, photocurrent / event count (goal: at least 0.5). EventCount runs at
   its default threshold 1, PhotocurrentPooling at its defaults (contrast 0.2, threshold 0.2).
   The frames mode at 1000 fps is timed beside them for reference.
2. Memory of the frames mode: a 1280x720 stream of ``--long-events`` (10M) events over
   ``--long-seconds`` (5 s) at 1000 fps, factor 4, one call in a fresh process
   (:func:`evdown_torch.bench.measure_memory`): peak resident memory (goal: under 4 GB). A
   dense ``T x H x W`` float64 video of it would take 5000 x 921,600 x 8 B = 37 GB.

Run: ``python benchmarks/bench_photocurrent.py [--events N] [--repeats R] [--long-events N]
[--long-seconds S]``. The full run (the defaults) takes a few minutes on a quiet machine; a
quick check: ``--events 20000 --repeats 2 --long-events 200000``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch

from evdown_torch import EventCount, PhotocurrentPooling, bench


def alternate_timings(calls: dict[str, object], events: np.ndarray, repeats: int) -> dict:
    """Median wall and CPU seconds of each call, the calls taking turns (one warm-up each)."""
    wall: dict[str, list[float]] = {name: [] for name in calls}
    cpu: dict[str, list[float]] = {name: [] for name in calls}
    for fn in calls.values():
        fn(events)
    for _ in range(repeats):
        for name, fn in calls.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            fn(events)
            wall[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
    return {name: (statistics.median(wall[name]), statistics.median(cpu[name]))
            for name in calls}


def speed(num_events: int, repeats: int) -> None:
    print(f"events mode vs EventCount: {num_events:,} events, one thread, median of "
          f"{repeats} alternating runs (M events/s by wall clock; CPU in brackets)")
    print("| stream | factor | EventCount | Photocurrent (events) | ratio (CPU) | "
          "Photocurrent (frames, 1000 fps) |")
    print("|---|---|---|---|---|---|")
    for sensor in ((128, 128, 2), (1280, 720, 2)):
        events = bench.dvs_like_stream(num_events, sensor, duration_us=5_000_000, seed=3)
        for factor in (2, 4):
            calls = {
                "count": EventCount(sensor, factor=factor),
                "events": PhotocurrentPooling(sensor, factor=factor),
                "frames": PhotocurrentPooling(sensor, factor=factor, fps=1000.0),
            }
            times = alternate_timings(calls, events, repeats)
            rate = {name: num_events / wall / 1e6 for name, (wall, _) in times.items()}
            cpu_rate = {name: num_events / c / 1e6 for name, (_, c) in times.items()}
            print(f"| {sensor[0]}x{sensor[1]} | {factor} | {rate['count']:.2f} "
                  f"({cpu_rate['count']:.2f}) | {rate['events']:.2f} ({cpu_rate['events']:.2f}) "
                  f"| {rate['events'] / rate['count']:.2f} "
                  f"({cpu_rate['events'] / cpu_rate['count']:.2f}) | {rate['frames']:.2f} "
                  f"({cpu_rate['frames']:.2f}) |")


def memory(num_events: int, seconds: int) -> int:
    sensor = (1280, 720, 2)
    events = bench.dvs_like_stream(num_events, sensor, duration_us=seconds * 1_000_000,
                                   seed=5, num_objects=12)
    result = bench.fresh_call("photocurrent:fps=1000.0", events, sensor, 4)
    print(f"\nframes mode, 1280x720, {num_events:,} events over {seconds} s, 1000 fps, "
          f"factor 4, one call in a fresh process (goal: process peak under 4 GB):\n"
          f"  {bench.fresh_call_summary(result, num_events)}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--events", type=int, default=2_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--long-events", type=int, default=10_000_000)
    parser.add_argument("--long-seconds", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    speed(args.events, args.repeats)
    return memory(args.long_events, args.long_seconds) if args.long_events > 0 else 0


if __name__ == "__main__":
    sys.exit(main())
