"""Synthetic gesture rendering speed, one thread: 6 s at 128x128, ground truth, and 1280x720.

Run: ``python benchmarks/bench_synthetic.py [--repeats R] [--big-duration-us D]``.

* every class, a 6 s 128x128 sample through ``SyntheticGestures[i]`` (scene, rendering,
  noise, refractory, structured array): events, median wall and CPU seconds over the
  repeats, events per CPU second;
* the same samples' low-resolution ground truth at factors 2 and 4;
* one 1280x720 sample (right arm circles, the busiest class), in a fresh process so that its
  peak resident memory is its own: seconds, events, events/s, peak RSS.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import torch

from evdown_torch.synthetic import GESTURE_CLASSES, SyntheticGestures


def median_seconds(fn, repeats: int) -> tuple[float, float, object]:
    """Median wall-clock and median CPU seconds of ``fn()`` (after a warm-up), and its result.

    On a shared machine the wall clock also counts waiting for a core; the process's CPU
    time does not, so it is the better figure of the work itself.
    """
    out = fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall), statistics.median(cpu), out


def big(duration_us: int) -> None:
    """Render one 1280x720 sample and print a JSON line (run in its own process)."""
    torch.set_num_threads(1)
    data = SyntheticGestures(samples_per_class=1, duration_us=duration_us,
                             sensor_size=(1280, 720, 2))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start, start_cpu = time.perf_counter(), time.process_time()
    events, _ = data[3]
    seconds, cpu = time.perf_counter() - start, time.process_time() - start_cpu
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    print(json.dumps({"seconds": seconds, "cpu": cpu, "events": len(events),
                      "peak_rss_mib": peak / 1024, "rss_before_mib": before / 1024}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--big-duration-us", type=int, default=6_000_000)
    parser.add_argument("--skip-big", action="store_true")
    parser.add_argument("--big-only", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.big_only:
        big(args.big_duration_us)
        return
    torch.set_num_threads(1)
    data = SyntheticGestures(samples_per_class=1, duration_us=6_000_000)
    print(f"6 s, 128x128, one thread, median of {args.repeats} (SyntheticGestures[i])")
    print(f"{'class':<18} {'events':>8} {'wall s':>7} {'cpu s':>6} {'Mev/s':>6} "
          f"{'f=2 cpu':>8} {'f=4 cpu':>8}")
    walls, cpus, rates = [], [], []
    for index, name in enumerate(GESTURE_CLASSES):
        wall, cpu, (events, _) = median_seconds(lambda i=index: data[i], args.repeats)
        _, gt2, _ = median_seconds(lambda i=index: data.ground_truth(i, 2), 1)
        _, gt4, _ = median_seconds(lambda i=index: data.ground_truth(i, 4), 1)
        walls.append(wall)
        cpus.append(cpu)
        rates.append(len(events) / cpu)
        print(f"{name:<18} {len(events):>8} {wall:7.3f} {cpu:6.3f} {len(events) / cpu / 1e6:6.2f} "
              f"{gt2:8.3f} {gt4:8.3f}")
    print(f"over classes: wall median {statistics.median(walls):.3f} s (max {max(walls):.3f}), "
          f"cpu median {statistics.median(cpus):.3f} s (max {max(cpus):.3f}), "
          f"{statistics.median(rates) / 1e6:.2f} M events per cpu second")
    if args.skip_big:
        return
    result = subprocess.run(
        [sys.executable, __file__, "--big-only", "--big-duration-us", str(args.big_duration_us)],
        capture_output=True, text=True, check=True,
    )
    stats = json.loads(result.stdout.strip().splitlines()[-1])
    print(f"1280x720, {args.big_duration_us / 1e6:g} s, right arm cw, one thread: "
          f"{stats['events']} events in {stats['seconds']:.1f} s wall, {stats['cpu']:.1f} s cpu "
          f"({stats['events'] / stats['cpu'] / 1e6:.2f} M events per cpu second), "
          f"peak RSS {stats['peak_rss_mib']:.0f} MiB (process start {stats['rss_before_mib']:.0f})")


if __name__ == "__main__":
    main()
