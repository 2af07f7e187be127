"""``evdown bench``: its arguments (:func:`add_command`); run the benchmark, write the report."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import cast

import numpy as np

from evdown_torch.arguments import (
    Subparsers,
    add_file_format_options,
    add_out_option,
    add_sensor_size_option,
)
from evdown_torch.bench.inputs import BenchInput
from evdown_torch.bench.report import method_table, write_report
from evdown_torch.bench.run import run_benchmark
from evdown_torch.checks import check_positive_int

__all__ = ["add_command", "run_from_args"]

def add_command(commands: Subparsers) -> None:
    """Register ``evdown bench`` on the ``evdown`` subparsers."""
    bench = commands.add_parser(
        "bench", help="benchmark every method against its peers; write a report and plots",
        description="Time every downscaling method, and its peers in Tonic, on a synthetic "
        "gesture recording, a large 1280x720 stream and any --input files, at factors 2 to "
        "8, with one torch thread (median of several calls); then sweep events, sensor size "
        "and duration, and measure peak memory in a fresh process. Writes report.md, "
        "results.json and PNG plots to --out; a progress bar per stage on a terminal. "
        "--short takes under 2 minutes; the full run tens of minutes.",
    )
    add_out_option(bench, "folder for report.md, results.json and the PNG plots")
    bench.add_argument("--short", action="store_true",
                       help="small inputs and two points per sweep (under 2 minutes)")
    bench.add_argument("--input", action="append", metavar="FILE",
                       help="an event file to add to the method table (repeatable; any format "
                       "evdown reads)")
    add_sensor_size_option(bench, "sensor of the --input files that do not record one "
                           "(default: guessed from the largest coordinates, with a warning)")
    add_file_format_options(bench)  # --time-unit, --columns of the --input files
    bench.add_argument("--events", type=int, metavar="N",
                       help="cap every stream at N events (quick checks)")
    bench.add_argument("--repeats", type=int, metavar="R",
                       help="timed calls per measurement of the method table (default 5)")
    bench.add_argument("--methods", nargs="+", metavar="SPEC",
                       help="only these methods and peers (default: all): NAME or "
                       "NAME:KEY=VALUE,... for a method with other settings, e.g. "
                       "lif:weight=1.5; peers: tonic_downsample, tonic_integrator, "
                       "tonic_differentiator")
    bench.add_argument("--no-scaling", action="store_true", help="skip the scaling sweeps")
    bench.add_argument("--no-memory", action="store_true", help="skip peak-memory measurements")
    bench.add_argument("--realtime", action="store_true",
                       help="replay a recording (the first --input, else a synthetic gesture "
                       "one) through every streaming session in 1, 2 and 10 ms chunks, at its "
                       "own rate and at 25 M events/s, with each method's latency budget "
                       "(algorithmic delay + chunk + p99 processing time); writes "
                       "realtime.md/.json/.png")
    bench.set_defaults(run=run_from_args)


def run_from_args(args: argparse.Namespace, *, nmnist: str | Path | None = None) -> int:
    """Run ``evdown bench`` from its parsed arguments (:func:`add_command`); the exit status.

    Runs :func:`~evdown_torch.bench.run.run_benchmark` with the parsed options (and the
    N-MNIST recording ``nmnist``, when given), writes the report to ``args.out`` and prints
    the headline table.
    """
    if args.events is not None:
        check_positive_int("--events", args.events)
    if getattr(args, "realtime", False):
        return _realtime_from_args(args)
    results = run_benchmark(
        short=args.short, inputs=args.input or (), sensor_size=args.sensor_size,
        events=args.events, repeats=args.repeats, methods=args.methods,
        scaling=not args.no_scaling, memory=not args.no_memory, nmnist=nmnist,
        time_unit=args.time_unit, columns=args.columns,
    )
    command = "evdown bench " + " ".join(sys.argv[2:]) if len(sys.argv) > 1 else ""
    written = write_report(results, args.out, command=command)
    headline = cast(BenchInput, results.input("gesture"))  # always measured
    print(f"gesture: {headline.sensor_size[0]}x{headline.sensor_size[1]}, "
          f"{headline.num_events:,} events\n{method_table(results, 'gesture')}")
    print(f"evdown bench: {len(results.measurements)} measurements in "
          f"{results.elapsed_s:.0f} s; wrote {', '.join(str(p) for p in written)}")
    return 0


def _realtime_from_args(args: argparse.Namespace) -> int:
    """``evdown bench --realtime``: replay a recording through every session in live chunks."""
    from evdown_torch.bench.inputs import gesture_stream
    from evdown_torch.bench.realtime import (
        REALTIME_RATE,
        allocator_settings,
        realtime_benchmark,
        write_realtime_report,
    )
    from evdown_torch.io import read_microseconds

    start = time.perf_counter()
    if args.input:
        recording = read_microseconds(args.input[0], sensor_size=args.sensor_size,
                                      time_unit=args.time_unit,
                                      **({"columns": args.columns} if args.columns else {}))
        events = np.sort(recording.events, order="t", kind="stable")
        sensor = recording.sensor_size
        source = f"{args.input[0]}"
    else:
        # Enough events for the timed chunks at 25 M events/s in 10 ms chunks.
        n = args.events or (1_000_000 if args.short else 13_000_000)
        sensor = (128, 128, 2)
        events = gesture_stream(n, sensor_size=sensor)
        source = f"synthetic DVS128-Gesture-like recording ({len(events):,} events)"
    max_chunks = 10 if args.short else 50
    results = realtime_benchmark(events, sensor, methods=args.methods, max_chunks=max_chunks)
    header = (
        f"Real-time replay of {source}, {sensor[0]}x{sensor[1]}, factor 4, one thread; "
        f"at its own rate and at {REALTIME_RATE / 1e6:g} M events/s; up to {max_chunks} timed "
        f"chunks per replay; {time.perf_counter() - start:.0f} s. Memory allocator: "
        f"{allocator_settings()}.\n\n"
    )
    written = write_realtime_report(results, args.out, header=header)
    print(header + (Path(written[0]).read_text()[len(header):]))
    print(f"evdown bench --realtime: wrote {', '.join(str(p) for p in written)}")
    return 0
