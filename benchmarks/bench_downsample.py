"""Downsample and EventFunnelling against tonic.transforms.Downsample (issue 2's goals).

Run: ``python benchmarks/bench_downsample.py [--out DIR] [--events N] [--repeats R] [--short]``;
a thin wrapper of ``evdown bench --methods downsample funnelling tonic_downsample
--no-scaling`` (the shared harness :mod:`evdown_torch.bench`); the report goes to
``benchmarks/results/downsample`` unless ``--out`` is given.
"""

from __future__ import annotations

import sys
from pathlib import Path

from bench_all import run_bench

METHODS = ["downsample", "funnelling", "tonic_downsample"]

if __name__ == "__main__":
    args = sys.argv[1:]
    if "--out" not in args:
        args += ["--out", str(Path(__file__).parent / "results" / "downsample")]
    sys.exit(run_bench(["--methods", *METHODS, "--no-scaling", *args]))
