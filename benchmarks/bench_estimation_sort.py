"""Estimator batch kernels against a stable sort of the same keys, in the same run (issue 29).

Times LinearEstimation and CubicEstimation (with and without ``max_delay``) on the 1M-event
synthetic gesture stream (:func:`evdown_torch.bench.inputs.gesture_stream`, 128x128) and, in
the same process, a stable ``torch.sort`` of the stream's int64 region keys: a yardstick that
takes the machine's current speed out of the figures (this machine is shared and busy). One
thread; each figure is the median of ``--repeats`` calls, and the script prints each method's
time as a multiple of the sort's, for ``--runs`` runs and their median.

Run: ``python benchmarks/bench_estimation_sort.py [--events N] [--runs 3] [--repeats 5]``.
It can also write each output (``--save DIR``) so that two commits can be checked equal.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from evdown_torch import CubicEstimation, LinearEstimation
from evdown_torch.bench.inputs import gesture_stream

SENSOR = (128, 128, 2)


def median_seconds(call, repeats: int) -> float:
    call()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--factor", type=int, default=4)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--save", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    arr = gesture_stream(args.events, sensor_size=SENSOR)
    ev = torch.from_numpy(np.stack([arr["x"].astype(np.int64), arr["y"].astype(np.int64),
                                    arr["t"], arr["p"].astype(np.int64)], 1))
    f = args.factor
    keys = (ev[:, 1] // f) * ((SENSOR[0] + f - 1) // f) + ev[:, 0] // f
    methods = {
        "linear": LinearEstimation(SENSOR, f, threshold=1.0),
        "cubic": CubicEstimation(SENSOR, f, threshold=1.0),
        "linear D=3000": LinearEstimation(SENSOR, f, threshold=1.0, max_delay=3000),
        "cubic D=3000": CubicEstimation(SENSOR, f, threshold=1.0, max_delay=3000),
    }
    if args.save is not None:
        args.save.mkdir(parents=True, exist_ok=True)
        for name, transform in methods.items():
            np.save(args.save / f"{name.replace(' ', '_')}.npy", transform(ev).numpy())
    ratios: dict[str, list[float]] = {name: [] for name in methods}
    for run in range(args.runs):
        sort = median_seconds(lambda: torch.sort(keys, stable=True), args.repeats)
        line = [f"run {run + 1}: sort {sort * 1e3:.1f} ms"]
        for name, transform in methods.items():
            seconds = median_seconds(lambda transform=transform: transform(ev), args.repeats)
            ratios[name].append(seconds / sort)
            line.append(f"{name} {seconds * 1e3:.0f} ms ({seconds / sort:.1f}x)")
        print("; ".join(line), flush=True)
    for name, values in ratios.items():
        print(f"{name}: x sort {', '.join(f'{v:.1f}' for v in values)}; "
              f"median {statistics.median(values):.1f}")


if __name__ == "__main__":
    main()
