"""Tiny thresholds: the log-luminance methods cost what their output costs.

A threshold far below a region's level steps makes every input event cross many levels, so the
output can be thousands of times the input. The kernels count it before building it (and
refuse it above the limit of ``evdown_torch.max_output_events``); this script shows that the
time per output event stays flat as the threshold shrinks (300 random events on an 8x8 sensor
over 0.1 s, factor 2, one thread).

Run: ``python benchmarks/bench_thresholds.py [--smallest 1e-5] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from evdown_torch import CubicEstimation, EventCount, LinearEstimation
from evdown_torch.events import DVS_DTYPE


def stream(n: int = 300, seed: int = 0) -> np.ndarray:
    """``n`` random events on an 8x8 sensor over 0.1 s, sorted by time."""
    rng = np.random.default_rng(seed)
    ev = np.zeros(n, DVS_DTYPE)
    ev["x"], ev["y"] = rng.integers(0, 8, n), rng.integers(0, 8, n)
    ev["p"] = rng.random(n) < 0.5
    ev["t"] = np.sort(rng.integers(0, 100_000, n))
    return ev


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smallest", type=float, default=1e-5)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    ev = stream()
    thresholds = [t for t in (1e-2, 1e-3, 1e-4, 1e-5, 1e-6) if t >= args.smallest]
    print("| method | threshold | events out | median CPU s | ns per output event |")
    print("|---|---|---|---|---|")
    for method in (EventCount, LinearEstimation, CubicEstimation):
        for threshold in thresholds:
            transform = method((8, 8, 2), 2, threshold=threshold)
            times = []
            for _ in range(args.repeats):
                start = time.process_time()
                out = transform(ev)
                times.append(time.process_time() - start)
            seconds = statistics.median(times)
            print(f"| {method.__name__} | {threshold:g} | {len(out):,} | {seconds:.3f} | "
                  f"{seconds / max(len(out), 1) * 1e9:.0f} |")


if __name__ == "__main__":
    main()
