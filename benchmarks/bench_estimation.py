"""LinearEstimation and CubicEstimation (EventCount as a peer): speed and peak memory.

Speed: one thread, median of several runs (wall clock and process CPU time), Tonic
structured array in and out (conversions included), 128x128 sensor, factor 4, two random
DVS-like streams of the same size: a dense one (about two events per microsecond, so
timestamps repeat) and one at a DVS-Gesture-like rate (200,000 events per second).

Memory: each method on a 1280x720 stream of 10M events at factor 4, in a fresh subprocess,
peak resident memory from ``resource.getrusage``.

Run: ``python benchmarks/bench_estimation.py [--events N] [--repeats R] [--no-memory]``.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

from evdown_torch import CubicEstimation, EventCount, LinearEstimation

DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("p", bool), ("t", np.int64)])
METHODS = {"EventCount": EventCount, "LinearEstimation": LinearEstimation,
           "CubicEstimation": CubicEstimation}
#: The paper's reference code, seconds per 100,000 events (Gruel et al., VISAPP 2022).
PAPER_SECONDS_PER_100K = {"EventCount": 0.8, "LinearEstimation": 2.6, "CubicEstimation": 2.9}
EPOCH = 1_700_000_000_000_000  # Unix-epoch microseconds, as recorded by real cameras


def stream(n: int, sensor: tuple[int, int], duration_us: int, seed: int = 0) -> np.ndarray:
    """``n`` uniformly random events over ``duration_us`` microseconds, sorted by time."""
    rng = np.random.default_rng(seed)
    out = np.empty(n, dtype=DTYPE)
    out["x"] = rng.integers(0, sensor[0], n)
    out["y"] = rng.integers(0, sensor[1], n)
    out["p"] = rng.random(n) < 0.5
    out["t"] = EPOCH + np.sort(rng.integers(0, duration_us, n))
    return out


def median_seconds(fn, data, repeats: int) -> tuple[float, float]:
    """Median wall-clock and median process CPU seconds of ``fn(data)`` (after a warm-up).

    With one thread the two agree on a quiet machine; on a shared one, CPU time is the less
    disturbed figure.
    """
    fn(data)  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn(data)
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall), statistics.median(cpu)


def memory_worker(method: str, events: int) -> None:
    """Run one method on a 1280x720 stream in this process and print its figures as JSON."""
    torch.set_num_threads(1)
    data = stream(events, (1280, 720), duration_us=events // 2)  # 2 events per microsecond
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    out = METHODS[method]((1280, 720, 2), factor=4)(data)
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    print(json.dumps({"method": method, "events": events, "output": len(out),
                      "seconds": seconds, "input_mib": before / 1024, "peak_mib": peak / 1024}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--memory-events", type=int, default=10_000_000)
    parser.add_argument("--no-memory", action="store_true")
    parser.add_argument("--memory-worker", choices=list(METHODS), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.memory_worker:
        memory_worker(args.memory_worker, args.memory_events)
        return
    torch.set_num_threads(1)
    sensor = (128, 128, 2)
    streams = {
        "dense (2 ev/us)": stream(args.events, sensor[:2], duration_us=args.events // 2),
        "200k ev/s": stream(args.events, sensor[:2], duration_us=args.events * 5),
    }
    print(f"{args.events} events, 128x128, factor 4, threshold 1, one thread, "
          f"median of {args.repeats}")
    print(f"{'method':<18} {'stream':<16} {'wall s':>7} {'M ev/s':>7} {'cpu s':>7} "
          f"{'M ev/s':>7} {'vs paper':>9}")
    for name, cls in METHODS.items():
        transform = cls(sensor, factor=4)
        paper_rate = 100_000 / PAPER_SECONDS_PER_100K[name]
        for label, data in streams.items():
            wall, cpu = median_seconds(transform, data, args.repeats)
            rate, cpu_rate = args.events / wall, args.events / cpu
            print(f"{name:<18} {label:<16} {wall:7.3f} {rate / 1e6:7.2f} {cpu:7.3f} "
                  f"{cpu_rate / 1e6:7.2f} {rate / paper_rate:8.0f}x")
    if args.no_memory:
        return
    print(f"\npeak memory, 1280x720, {args.memory_events} events (2 ev/us), factor 4, "
          "one subprocess per method")
    print(f"{'method':<18} {'seconds':>8} {'input MiB':>10} {'peak MiB':>9} {'outputs':>8}")
    for name in METHODS:
        result = subprocess.run(
            [sys.executable, __file__, "--memory-worker", name,
             "--memory-events", str(args.memory_events)],
            check=True, capture_output=True, text=True,
        )
        r = json.loads(result.stdout.strip().splitlines()[-1])
        print(f"{name:<18} {r['seconds']:8.2f} {r['input_mib']:10.0f} {r['peak_mib']:9.0f} "
              f"{r['output']:8d}")


if __name__ == "__main__":
    main()
