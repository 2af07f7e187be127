"""One torch thread against all of them, per method, through the ``evdown downscale`` command.

Run: ``python benchmarks/bench_threads.py [--repeats R] [--threads N] [--methods a,b,...]``.
It writes a synthetic DVS gesture recording (128 x 128, 2 s) to a temporary folder, and for
each method and each input (that recording and the real N-MNIST sample of
``/work/shared/data``, when there) runs ``python -m evdown_torch downscale IN OUT --method M
--factor 4 --threads T`` for ``T`` = 1 and ``T`` = all cores (default: the cores this process
may use), alternating, ``R`` times each (default 5). It prints the medians of the downscaling
time the command reports (the transform call alone) and of the whole command's wall time, and
their ratios (all threads / one thread: above 1, one thread is faster), as a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from evdown_torch.synthetic import render_gesture
from evdown_torch.transforms.registry import METHODS

NMNIST = Path("/work/shared/data/sample_nmnist.bin")
SECONDS = re.compile(r", ([0-9.]+) s \(")


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def _run(source: Path, out: Path, method: str, threads: int, extra: list[str]) -> tuple[
        float, float]:
    command = [sys.executable, "-m", "evdown_torch", "downscale", str(source), str(out),
               "--method", method, "--factor", "4", "--threads", str(threads), *extra]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - start
    return float(SECONDS.search(done.stdout).group(1)), wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=_cores(), help="'all' threads")
    parser.add_argument("--methods", default=",".join(METHODS))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        gesture = Path(folder) / "gesture.npy"
        events = render_gesture(3, 0, sensor_size=(128, 128, 2), duration_us=2_000_000)
        np.save(gesture, events)
        inputs = [(f"gesture 128x128, {len(events):,} events", gesture,
                   ["--sensor-size", "128", "128", "2"])]
        if NMNIST.is_file():
            inputs.append(("N-MNIST sample, 4,325 events", NMNIST, ["--sensor-size", "34", "34",
                                                                    "2"]))
        print(f"{_cores()} cores; 'all' = {args.threads} threads; medians of {args.repeats} "
              "runs; ratio = all threads / 1 thread")
        print("| input | method | 1 thread: call (ms) | all: call (ms) | call ratio | "
              "1 thread: command (s) | all: command (s) | command ratio |")
        print("|---|---|---|---|---|---|---|---|")
        for label, source, extra in inputs:
            for method in args.methods.split(","):
                times = {1: [], args.threads: []}
                for _ in range(args.repeats):
                    for threads in times:  # alternating, so load changes hit both alike
                        times[threads].append(_run(source, Path(folder) / "out.npy", method,
                                                   threads, extra))
                one = [statistics.median(v) for v in zip(*times[1])]
                all_ = [statistics.median(v) for v in zip(*times[args.threads])]
                print(f"| {label} | {method} | {one[0] * 1e3:.1f} | {all_[0] * 1e3:.1f} | "
                      f"{all_[0] / one[0]:.2f} | {one[1]:.2f} | {all_[1]:.2f} | "
                      f"{all_[1] / one[1]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
