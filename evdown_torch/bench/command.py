"""``evdown bench``: run the benchmark from the command line's arguments, write the report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from evdown_torch.bench.report import method_table, write_report
from evdown_torch.bench.run import run_benchmark
from evdown_torch.checks import check_positive_int

__all__ = ["run_from_args"]

def run_from_args(args: argparse.Namespace, *, nmnist: str | Path | None = None) -> int:
    """The ``evdown bench`` command (see :func:`evdown_torch.cli.build_parser`).

    Runs :func:`~evdown_torch.bench.run.run_benchmark` with the parsed options (and the
    N-MNIST recording ``nmnist``, when given), writes the report to ``args.out`` and prints
    the headline table.
    """
    if args.events is not None:
        check_positive_int("--events", args.events)
    results = run_benchmark(
        short=args.short, inputs=args.input or (), sensor_size=args.sensor_size,
        events=args.events, repeats=args.repeats, methods=args.methods,
        scaling=not args.no_scaling, memory=not args.no_memory, nmnist=nmnist,
    )
    command = "evdown bench " + " ".join(sys.argv[2:]) if len(sys.argv) > 1 else ""
    written = write_report(results, args.out, command=command)
    headline = results.input("gesture")
    print(f"gesture: {headline.sensor_size[0]}x{headline.sensor_size[1]}, "
          f"{headline.num_events:,} events\n{method_table(results, 'gesture')}")
    print(f"evdown bench: {len(results.measurements)} measurements in "
          f"{results.elapsed_s:.0f} s; wrote {', '.join(str(p) for p in written)}")
    return 0
