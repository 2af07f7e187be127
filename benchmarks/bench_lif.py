"""LIFPooling speed: flat across sensor size and duration, with EventCount as the peer.

1. Scaling rows (always): 100k uniformly random events (``--events``) at factor 4 on a
   128x128 and a 1280x720 sensor, spread over 1 s and over 10 s, LIFPooling with its defaults
   (``dt`` = 1 ms, ``tau`` = 10 ms) and EventCount (threshold 1) timed in the same run, one
   thread, best of ``--repeats`` calls on a Tonic structured array. An event-driven kernel is
   flat across the rows; a kernel that steps every neuron through every active step costs
   ``steps x regions`` and falls by 40x from the first row to the last. Goals: at least 2 M
   events/s in every row, and the 1280x720 10 s row within 2x of the 128x128 1 s row.
2. ``--harness``: ``evdown bench --methods downsample lif <variants> --no-scaling`` (the
   shared harness, :mod:`evdown_torch.bench`), report to ``--out``.
3. ``--long-seconds S``: one call on a 1280x720 recording of ``S`` seconds at ``--long-rate``
   events/s in a fresh process (the harness's memory measurement): time and peak memory.

Run: ``python benchmarks/bench_lif.py [--events N] [--repeats R] [--short] [--harness]
[--long-seconds S]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from evdown_torch import EventCount, LIFPooling

DTYPE = np.dtype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")])
ROWS = [((128, 128), 1), ((128, 128), 10), ((1280, 720), 1), ((1280, 720), 10)]
VARIANTS = [
    "downsample",
    "lif",
    "lif:mutual_inhibition=0.3,reset_mechanism=zero",
    "lif:weight=1.5",
]


def random_events(n: int, size: tuple[int, int], seconds: int, seed: int) -> np.ndarray:
    """``n`` uniformly random events on a ``W x H`` sensor over ``seconds``, in microseconds."""
    rng = np.random.default_rng(seed)
    events = np.zeros(n, dtype=DTYPE)
    events["x"] = rng.integers(0, size[0], n)
    events["y"] = rng.integers(0, size[1], n)
    events["p"] = rng.random(n) < 0.5
    events["t"] = np.sort(rng.integers(0, seconds * 1_000_000, n))
    return events


def best_time(transform, events: np.ndarray, repeats: int) -> tuple[float, int]:
    """Best wall time of ``repeats`` calls (after one warm-up) and the output size."""
    out = transform(events)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        transform(events)
        best = min(best, time.perf_counter() - start)
    return best, len(out)


def scaling_rows(n: int, repeats: int) -> int:
    """Print the table of the four rows and whether the goals are met; 0 if they are."""
    print(f"LIFPooling (defaults: dt = 1 ms, tau = 10 ms) and EventCount (threshold 1), "
          f"{n:,} random events, factor 4, {torch.get_num_threads()} thread(s), "
          f"best of {repeats}:\n")
    print("| sensor, duration | LIFPooling | EventCount | LIF events out |")
    print("|---|---|---|---|")
    rates = {}
    for seed, (size, seconds) in enumerate(ROWS):
        events = random_events(n, size, seconds, seed)
        sensor = (*size, 2)
        lif_s, lif_out = best_time(LIFPooling(sensor, 4), events, repeats)
        count_s, _ = best_time(EventCount(sensor, 4), events, repeats)
        rates[size, seconds] = n / lif_s / 1e6
        print(f"| {size[0]}x{size[1]}, {seconds} s | {rates[size, seconds]:.2f} M events/s "
              f"| {n / count_s / 1e6:.2f} M events/s | {lif_out:,} |")
    lowest = min(rates.values())
    flat = rates[(128, 128), 1] / rates[(1280, 720), 10]
    print(f"\nslowest row: {lowest:.2f} M events/s (goal >= 2): "
          f"{'met' if lowest >= 2 else 'missed'}")
    print(f"128x128 1 s / 1280x720 10 s: {flat:.2f}x (goal <= 2): "
          f"{'met' if flat <= 2 else 'missed'}")
    return 0 if lowest >= 2 and flat <= 2 else 1


def long_recording(seconds: int, rate: float) -> int:
    """Time and peak memory of one call on a long 1280x720 recording, in a fresh process."""
    from evdown_torch import bench

    events = np.concatenate([
        bench.dvs_like_stream(int(rate), (1280, 720, 2), duration_us=1_000_000, seed=5,
                              num_objects=12, start_us=s * 1_000_000)
        for s in range(seconds)
    ])
    result = bench.fresh_call("lif", events, (1280, 720, 2), 4)
    print(f"\nlong recording: 1280x720, {seconds} s, {len(events):,} events, factor 4, "
          f"dt = 1 ms, defaults, one call in a fresh process:\n"
          f"  {bench.fresh_call_summary(result, len(events))}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--events", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--short", action="store_true", help="one repeat, 20k events")
    parser.add_argument("--harness", action="store_true", help="also run the harness variants")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "lif"))
    parser.add_argument("--long-seconds", type=int, default=0)
    parser.add_argument("--long-rate", type=float, default=1_000_000.0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    n, repeats = (20_000, 1) if args.short else (args.events, args.repeats)
    code = scaling_rows(n, repeats)
    if args.harness:
        from evdown_torch.cli import main as evdown

        code |= evdown(["bench", "--out", args.out, "--methods", *VARIANTS, "--no-scaling",
                        *(["--short"] if args.short else [])])
    if args.long_seconds > 0:
        code |= long_recording(args.long_seconds, args.long_rate)
    return code


if __name__ == "__main__":
    sys.exit(main())
