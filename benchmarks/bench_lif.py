"""LIFPooling speed and memory (issue 5), through the shared harness :mod:`evdown_torch.bench`.

1. Speed: ``evdown bench --methods downsample lif <variants> --no-scaling``: the harness's
   DVS128-Gesture-like stream (and the other inputs of the method table), factor 2 and 4,
   ``dt`` = 1 ms, one thread; the defaults and three variants (mutual inhibition with reset to
   zero, a dense-output weight).
2. Memory of a long recording: a 1280x720 stream of moving bar edges at ``--long-rate``
   events/s for ``--long-seconds`` (60 s, 60M events by default), factor 4, ``dt`` = 1 ms,
   defaults: one call in a fresh process (:func:`evdown_torch.bench.measure_memory`), its
   time and peak resident memory. ``T x H x W`` tensors would need hundreds of GB here.

Run: ``python benchmarks/bench_lif.py [--out DIR] [--short] [--long-seconds S]
[--long-rate R]``; the report goes to ``benchmarks/results/lif`` unless ``--out`` is given.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from evdown_torch import bench
from evdown_torch.cli import main as evdown

VARIANTS = [
    "downsample",
    "lif",
    "lif:mutual_inhibition=0.3,reset_mechanism=zero",
    "lif:weight=1.5",
]


def long_recording(path: Path, seconds: int, rate: float) -> int:
    """Write a ``seconds``-long 1280x720 stream to ``path``, one second at a time; its size."""
    pieces = [
        bench.dvs_like_stream(int(rate), (1280, 720, 2), duration_us=1_000_000, seed=5,
                              num_objects=12, start_us=s * 1_000_000)
        for s in range(seconds)
    ]
    events = np.concatenate(pieces)
    np.save(path, events)
    return len(events)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "lif"))
    parser.add_argument("--short", action="store_true")
    parser.add_argument("--long-seconds", type=int, default=60)
    parser.add_argument("--long-rate", type=float, default=1_000_000.0)
    args = parser.parse_args()
    code = evdown(["bench", "--out", args.out, "--methods", *VARIANTS, "--no-scaling",
                   *(["--short"] if args.short else [])])
    if code or args.long_seconds <= 0:
        return code
    with tempfile.TemporaryDirectory(prefix="evdown-lif-") as tmp:
        path = Path(tmp) / "long.npy"
        n = long_recording(path, args.long_seconds, args.long_rate)
        [result] = bench.measure_memory([bench.candidate_job("lif", str(path), (1280, 720, 2), 4)])
    if "error" in result:
        print(f"long recording: {result['error']}", file=sys.stderr)
        return 1
    mib = 2**20
    print(f"\nlong recording: 1280x720, {args.long_seconds} s, {n:,} events, factor 4, "
          f"dt = 1 ms, defaults, one call in a fresh process:\n"
          f"  {result['seconds']:.1f} s ({result['cpu_seconds']:.1f} s CPU, "
          f"{n / result['seconds'] / 1e6:.2f} M events/s); peak memory "
          f"+{result['added'] / mib:,.0f} MiB during the call "
          f"({result['added'] / n:.1f} bytes per input event), process peak "
          f"{result['total'] / mib:,.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
