"""EventCount, LinearEstimation and CubicEstimation (issue 3), through the shared harness.

Runs ``evdown bench --methods event_count linear cubic --no-scaling`` (see
:mod:`evdown_torch.bench`: one thread, median of at least 5 calls, wall-clock and CPU time,
peak memory per method in a fresh process, the 1280x720 10M-event stream at factor 4 for the
memory goal) with two more inputs, uniformly random events on a 128x128 sensor with
Unix-epoch microsecond timestamps (about 1.7e15): a dense one (about two events per
microsecond, so timestamps repeat) and one at 200,000 events per second. The report's goals
table printed at the end gives the speed-up over the paper's reference code.

Run: ``python benchmarks/bench_estimation.py [--out DIR] [--events N] [--short]``; the report
goes to ``benchmarks/results/estimation`` unless ``--out`` is given.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_all import run_bench

from evdown_torch.events import DVS_DTYPE

EPOCH = 1_700_000_000_000_000  # Unix-epoch microseconds, as recorded by real cameras


def uniform_stream(n: int, duration_us: int, seed: int = 0) -> np.ndarray:
    """``n`` uniformly random 128x128 events over ``duration_us`` from ``EPOCH``, sorted."""
    rng = np.random.default_rng(seed)
    out = np.empty(n, dtype=DVS_DTYPE)
    out["x"] = rng.integers(0, 128, n)
    out["y"] = rng.integers(0, 128, n)
    out["p"] = rng.random(n) < 0.5
    out["t"] = EPOCH + np.sort(rng.integers(0, duration_us, n))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "estimation"))
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--short", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="evdown-estimation-") as tmp:
        dense, rate = Path(tmp) / "uniform-dense.npy", Path(tmp) / "uniform-200k.npy"
        np.save(dense, uniform_stream(args.events, max(args.events // 2, 1)))
        np.save(rate, uniform_stream(args.events, args.events * 5))
        return run_bench(["--out", args.out, "--methods", "event_count", "linear", "cubic",
                          "--no-scaling", "--input", str(dense), "--input", str(rate),
                          "--sensor-size", "128", "128", "2",
                          *(["--short"] if args.short else [])])


if __name__ == "__main__":
    sys.exit(main())
