"""The ``evdown`` command line.

Subcommands:

* ``evdown downscale IN OUT --method NAME --factor F [--threshold T] [--set KEY=VALUE ...]``:
  downscale a ``.npy`` structured event array (Tonic's format) into another.
* ``evdown bench --out DIR [--short] [--input FILE.npy ...]``: benchmark every method against
  its peers (Tonic), with scaling curves and peak memory; writes a Markdown report, JSON and
  PNG plots (see :mod:`evdown_torch.bench`).
* ``evdown evaluate --config FILE [--output DIR]``: measure every method's speed/accuracy
  trade (:mod:`evdown_torch.evaluation`) and write ``results.csv``, ``report.md`` and
  ``tradeoff.png``.
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from evdown_torch.events import load_npy_events
from evdown_torch.transforms.registry import METHODS, make_method


class CommandError(Exception):
    """A problem with the command's input, reported as one line without a traceback."""


def _factor(text: str) -> int | tuple[int, int]:
    parts = text.split(",")
    try:
        values = [int(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"factor must be F or FX,FY integers, got {text!r}"
        ) from None
    if len(values) == 1:
        return values[0]
    if len(values) == 2:
        return values[0], values[1]
    raise argparse.ArgumentTypeError(f"factor must be F or FX,FY integers, got {text!r}")


def _setting(text: str) -> tuple[str, Any]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"a setting must look like KEY=VALUE, got {text!r}")
    try:
        parsed = ast.literal_eval(value)
    except (ValueError, SyntaxError):
        parsed = value
    return key.replace("-", "_"), parsed


def _downscale(args: argparse.Namespace) -> int:
    events = load_npy_events(args.input)
    if args.sensor_size is not None:
        sensor_size = tuple(args.sensor_size)
    elif len(events) and {"x", "y"} <= set(events.dtype.names):
        sensor_size = (int(events["x"].max()) + 1, int(events["y"].max()) + 1, 2)
    else:
        raise CommandError("the sensor size cannot be inferred here: pass --sensor-size W H P")
    settings = dict(args.set or [])
    if args.threshold is not None:
        settings["threshold"] = args.threshold
    transform = make_method(args.method, sensor_size, args.factor, **settings)
    start = time.perf_counter()
    out = transform(events)
    seconds = time.perf_counter() - start
    np.save(args.output, out)
    rate = len(events) / seconds if seconds > 0 else float("inf")
    print(
        f"{args.method}: {len(events)} events in, {len(out)} events out "
        f"({len(out) / max(len(events), 1):.3f} of the input), sensor {sensor_size} -> "
        f"{transform.output_sensor_size}, {seconds:.3f} s ({rate / 1e6:.2f} M events/s); "
        f"wrote {args.output}"
    )
    return 0


def _bench(args: argparse.Namespace) -> int:
    from evdown_torch import bench

    return bench.run_from_args(args)


def _evaluate(args: argparse.Namespace) -> int:
    from evdown_torch.config import load_config
    from evdown_torch.evaluation import markdown_table, run_evaluation, write_report

    try:
        config = load_config(args.config)
        result = run_evaluation(config, cache=not args.no_cache)
    except (OSError, RuntimeError) as error:
        raise CommandError(str(error)) from None
    write_report(result, args.output or config.output.directory,
                 log=lambda line: print(line, file=sys.stderr))
    print(markdown_table(result), end="")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``evdown`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="evdown", description="Downscale event-camera streams (evdown_torch)."
    )
    commands = parser.add_subparsers(dest="command", required=True)
    down = commands.add_parser(
        "downscale", help="downscale a .npy structured event array into another"
    )
    down.add_argument("input", help="input .npy structured array with fields x, y, t, p")
    down.add_argument("output", help="output .npy path")
    down.add_argument("--method", required=True, choices=sorted(METHODS), metavar="NAME",
                      help=f"one of {', '.join(sorted(METHODS))}")
    down.add_argument("--factor", required=True, type=_factor, help="F or FX,FY")
    down.add_argument("--threshold", type=float, help="contrast threshold (log-luminance methods)")
    down.add_argument("--set", type=_setting, action="append", metavar="KEY=VALUE",
                      help="any other setting of the method, e.g. --set dt=1000")
    down.add_argument("--sensor-size", type=int, nargs=3, metavar=("W", "H", "P"),
                      help="input sensor size (default: from the largest coordinates)")
    down.set_defaults(run=_downscale)
    bench = commands.add_parser(
        "bench", help="benchmark every method against its peers; write a report and plots"
    )
    bench.add_argument("--out", required=True, metavar="DIR",
                       help="folder for report.md, results.json and the PNG plots")
    bench.add_argument("--short", action="store_true",
                       help="small inputs and two points per sweep (under 2 minutes)")
    bench.add_argument("--input", action="append", metavar="FILE.npy",
                       help="a structured event array to add to the method table (repeatable)")
    bench.add_argument("--sensor-size", type=int, nargs=3, metavar=("W", "H", "P"),
                       help="sensor of the --input files (default: from the largest coordinates)")
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
    bench.set_defaults(run=_bench)
    evaluate = commands.add_parser(
        "evaluate",
        help="train and test a spiking classifier on every method and factor; write a report",
    )
    evaluate.add_argument("--config", required=True, metavar="FILE",
                          help="TOML configuration, e.g. configs/quick.toml")
    evaluate.add_argument("--output", metavar="DIR",
                          help="output directory (default: the config's [output] directory)")
    evaluate.add_argument("--no-cache", action="store_true",
                          help="neither read nor keep the cache of recordings, frames and "
                          "predictions (work in a temporary directory)")
    evaluate.set_defaults(run=_evaluate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (CommandError, ValueError, TypeError) as error:
        print(f"evdown {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
