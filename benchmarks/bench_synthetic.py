"""Synthetic gesture rendering speed, one thread: 6 s at 128x128, ground truth, and 1280x720.

Run: ``python benchmarks/bench_synthetic.py [--repeats R] [--big-duration-us D] [--skip-big]``.
Timing and memory come from the shared harness :mod:`evdown_torch.bench`
(:func:`~evdown_torch.bench.time_call`, :func:`~evdown_torch.bench.measure_memory`).

* every class, a 6 s 128x128 sample through ``SyntheticGestures[i]`` (scene, rendering,
  noise, refractory, structured array): events, median wall and CPU seconds over the
  repeats, events per CPU second;
* the same samples' low-resolution ground truth at factors 2 and 4 (CPU seconds, one run);
* one 1280x720 sample (right arm circles, the busiest class), in a fresh process so that its
  peak resident memory is its own: seconds, events, events/s, peak memory.
"""

from __future__ import annotations

import argparse
import statistics

import torch

from evdown_torch.bench import MemoryJob, measure_memory, time_call
from evdown_torch.synthetic import GESTURE_CLASSES, SyntheticGestures


def prepare_big(duration_us: int):
    """Memory job: a 1280x720 dataset; the measured call renders sample 3 (right arm cw)."""
    data = SyntheticGestures(samples_per_class=1, duration_us=duration_us,
                             sensor_size=(1280, 720, 2))
    return lambda: len(data[3][0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--big-duration-us", type=int, default=6_000_000)
    parser.add_argument("--skip-big", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    data = SyntheticGestures(samples_per_class=1, duration_us=6_000_000)
    print(f"6 s, 128x128, one thread, median of {args.repeats} (SyntheticGestures[i])")
    print(f"{'class':<18} {'events':>8} {'wall s':>7} {'cpu s':>6} {'Mev/s':>6} "
          f"{'f=2 cpu':>8} {'f=4 cpu':>8}")
    walls, cpus, rates = [], [], []
    for index, name in enumerate(GESTURE_CLASSES):
        timing, (events, _) = time_call(data.__getitem__, index, repeats=args.repeats)
        gt2, _ = time_call(data.ground_truth, index, 2, repeats=1)
        gt4, _ = time_call(data.ground_truth, index, 4, repeats=1)
        walls.append(timing.seconds)
        cpus.append(timing.cpu_seconds)
        rates.append(len(events) / timing.cpu_seconds)
        print(f"{name:<18} {len(events):>8} {timing.seconds:7.3f} {timing.cpu_seconds:6.3f} "
              f"{rates[-1] / 1e6:6.2f} {gt2.cpu_seconds:8.3f} {gt4.cpu_seconds:8.3f}")
    print(f"over classes: wall median {statistics.median(walls):.3f} s (max {max(walls):.3f}), "
          f"cpu median {statistics.median(cpus):.3f} s (max {max(cpus):.3f}), "
          f"{statistics.median(rates) / 1e6:.2f} M events per cpu second")
    if args.skip_big:
        return
    [big] = measure_memory([MemoryJob(f"{__file__}:prepare_big",
                                      {"duration_us": args.big_duration_us})])
    if "error" in big:
        raise SystemExit(f"1280x720 sample: {big['error']}")
    mib = 2**20
    print(f"1280x720, {args.big_duration_us / 1e6:g} s, right arm cw, one thread, fresh "
          f"process: {big['result']:,} events in {big['seconds']:.1f} s wall, "
          f"{big['cpu_seconds']:.1f} s cpu "
          f"({big['result'] / big['cpu_seconds'] / 1e6:.2f} M events per cpu second), peak memory "
          f"+{big['added'] / mib:.0f} MiB during the call, process peak "
          f"{big['total'] / mib:.0f} MiB")


if __name__ == "__main__":
    main()
