"""Downsample and EventFunnelling against tonic.transforms.Downsample, one thread, 1M events.

Run: ``python benchmarks/bench_downsample.py [--events N] [--repeats R]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from evdown_torch import Downsample, EventFunnelling

DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("p", bool), ("t", np.int64)])


def stream(n: int, sensor=(128, 128, 2), seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.empty(n, dtype=DTYPE)
    out["x"] = rng.integers(0, sensor[0], n)
    out["y"] = rng.integers(0, sensor[1], n)
    out["p"] = rng.random(n) < 0.5
    out["t"] = np.sort(rng.integers(0, n // 2, n))  # ~2 events per microsecond, ties present
    return out


def median_seconds(fn, data, repeats: int) -> float:
    fn(data)  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn(data)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    torch.set_num_threads(1)
    data = stream(args.events)
    sensor = (128, 128, 2)
    rows = [("evdown Downsample", Downsample(sensor, factor=4)),
            ("evdown EventFunnelling", EventFunnelling(sensor, factor=4))]
    try:
        import tonic

        rows.insert(0, ("tonic Downsample", tonic.transforms.Downsample(spatial_factor=0.25)))
    except ImportError:
        pass
    print(f"{args.events} events, 128x128, factor 4, one thread, median of {args.repeats}")
    print(f"{'method':<24} {'seconds':>9} {'Mev/s':>8}")
    for name, fn in rows:
        s = median_seconds(fn, data, args.repeats)
        print(f"{name:<24} {s:9.4f} {args.events / s / 1e6:8.1f}")


if __name__ == "__main__":
    main()
