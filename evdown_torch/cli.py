"""The ``evdown`` command line.

Subcommands (``evdown COMMAND --help`` for each):

* ``evdown downscale IN [IN ...] OUT --method NAME --factor F [--set KEY=VALUE ...]``:
  downscale event files (any format :mod:`evdown_torch.io` reads, or folders of them) into
  ``.npy`` or HDF5 files.
* ``evdown bench --out DIR [--short] [--input FILE.npy ...]``: benchmark every method against
  its peers (Tonic) and write a report with plots (see :mod:`evdown_torch.bench`).
* ``evdown evaluate --config FILE [--output DIR]``: measure every method's speed/accuracy
  trade (:mod:`evdown_torch.evaluation`) and write ``results.csv``, ``report.md`` and
  ``tradeoff.png``.
* ``evdown preprocess --dataset NAME --method NAME --factor F --out DIR``: downscale a whole
  dataset once into a cache (see :mod:`evdown_torch.data`).
* ``evdown show IN --factor F [--out FILE.gif|FILE.png] [--curve X,Y]``: see what each method
  does (see :mod:`evdown_torch.plot.cli`).

Each subcommand is registered by one function in :data:`SUBCOMMANDS` that adds its parser
to the subparsers and sets ``run`` (a function of the parsed arguments returning the exit
status). A run that raises :class:`CommandError`, ``ValueError``, ``TypeError``,
``ImportError``, ``OSError`` or ``EOFError`` (a file that ends too soon) ends with the one
line ``evdown COMMAND: error: ...`` and exit status 2, as argparse does for bad arguments;
warnings print as ``evdown COMMAND: warning:``.
"""

from __future__ import annotations

import argparse
import os
import sys
import textwrap
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from evdown_torch import __version__
from evdown_torch._text import parse_factor, parse_setting
from evdown_torch.io import (
    READ_EXTENSIONS,
    check_columns,
    check_readable,
    check_writable,
    event_files,
    read_microseconds,
    write_events,
)
from evdown_torch.time_units import TIME_UNITS, check_timing, time_settings
from evdown_torch.transforms.registry import METHODS, make_method, method_settings

__all__ = ["SUBCOMMANDS", "CommandError", "build_parser", "main"]


class CommandError(Exception):
    """A problem with the command's input, reported as one line without a traceback."""


# ----------------------------------------------------------------------------- argument types


def _factor(text: str) -> int | tuple[int, int]:
    try:
        return parse_factor(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _setting(text: str) -> tuple[str, object]:
    try:
        return parse_setting(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _columns(text: str) -> tuple[str, ...]:
    try:
        return check_columns(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _threads(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"threads must be a positive integer, got {text!r}")
    return value


def add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options that say how to read input files and how many threads to use:
    ``--sensor-size``, ``--time-unit``, ``--columns`` and ``--threads``."""
    parser.add_argument("--sensor-size", type=int, nargs=3, metavar=("W", "H", "P"),
                        help="input sensor size for files that do not record one (.npy "
                        "without a sidecar, .bin, some .raw/.dat/HDF5); a file's own size "
                        "wins, so one value serves a mixed folder; else it is guessed with a "
                        "warning")
    parser.add_argument("--time-unit", choices=tuple(TIME_UNITS), metavar="UNIT",
                        help="unit of the input timestamps (s, ms, us, ns) for files that do "
                        "not state one (camera formats are us; a file's own unit wins); "
                        "timestamps are converted to microseconds, the unit of every time "
                        "setting (dt, tau, max_delay). Default: us")
    parser.add_argument("--columns", type=_columns, metavar="A,B,C,D",
                        help="column order of .npy files holding an (N, 4) array, e.g. "
                        "t,x,y,p (default x,y,t,p)")
    parser.add_argument("--threads", type=_threads, default=1, metavar="N",
                        help="torch threads (default 1: never much slower, often faster on a "
                        "busy machine; see docs/benchmarks.md)")


def read_input(
    path: Path, args: argparse.Namespace
) -> tuple[Any, tuple[int, int, int], str | None]:
    """Read an input file as the options of :func:`add_input_arguments` say
    (:func:`evdown_torch.io.read_microseconds`): ``(events, sensor_size, time_unit)``, ``t``
    in microseconds where the unit is known (``time_unit`` ``"us"``, else ``None``)."""
    recording = read_microseconds(path, sensor_size=args.sensor_size, time_unit=args.time_unit,
                                  **({"columns": args.columns} if args.columns else {}))
    return recording.events, recording.sensor_size, recording.time_unit


def _normal(name: str) -> str:
    return name.lower().replace("_", "").replace("-", "")


def _method(text: str) -> str:
    """A registry name from a registry name or a class name (``event_count``, ``EventCount``)."""
    aliases = {}
    for name, cls in METHODS.items():
        aliases[_normal(name)] = name
        aliases[_normal(cls.__name__)] = name
    name = aliases.get(_normal(text))
    if name is None:
        choices = ", ".join(f"{n} ({c.__name__})" for n, c in METHODS.items())
        raise argparse.ArgumentTypeError(f"unknown method {text!r}; choose one of {choices}")
    return name


def _methods_help() -> str:
    """Each method's names and its settings with their defaults: the valid ``--set`` keys."""
    lines = ["methods (--method takes either name) and their settings "
             "(--set KEY=VALUE; defaults shown):"]
    for name, cls in METHODS.items():
        defaults = {f.name: f for f in fields(cls)}
        items = []
        for key in method_settings(name):
            field = defaults[key]
            if field.default is not MISSING:
                items.append(f"{key}={field.default!r}")
            elif field.default_factory is not MISSING:
                items.append(f"{key}={field.default_factory()!r}")
            else:
                items.append(f"{key} (required)")
        text = " ".join(items) if items else "no settings"
        lines.append(textwrap.fill(text, width=92, initial_indent=f"  {name}, {cls.__name__}: ",
                                   subsequent_indent="      "))
    return "\n".join(lines)


# ----------------------------------------------------------------------------- downscale


def _say(text: str) -> None:
    """Print a line to stdout without breaking a progress bar."""
    tqdm.write(text, file=sys.stdout)


def _plan(paths: Sequence[str], output_format: str) -> list[tuple[Path, Path]]:
    """Pair each input file with its output path, checking everything before any work."""
    if len(paths) < 2:
        raise CommandError("give the input file(s) or folder(s), then the output")
    *inputs, output = (Path(p) for p in paths)
    files: list[Path] = []
    for path in inputs:
        if path.is_dir():
            found = event_files(path)
            if not found:
                raise CommandError(
                    f"folder {str(path)!r} holds no event files ({', '.join(READ_EXTENSIONS)})"
                )
            files += found
        else:
            files.append(check_readable(path))
    into_folder = (len(inputs) > 1 or inputs[0].is_dir() or output.is_dir()
                   or paths[-1].endswith(("/", os.sep)))  # "out/" names a folder to create
    folder = output if into_folder else output.parent
    for above in (folder, *folder.parents):  # the folder to create, and its missing parents
        if above.exists() and not above.is_dir():
            raise CommandError(f"cannot create {str(folder)!r}: {str(above)!r} is a file"
                               + ("; several inputs, a folder input or a trailing '/' need "
                                  "an output folder" if above == output else ""))
    if not into_folder:
        check_writable(output, folder_may_be_missing=True)
        pairs = [(files[0], output)]
    else:
        pairs = [(f, output / f"{f.stem}.{output_format}") for f in files]
        seen: dict[Path, Path] = {}
        for source, target in pairs:
            if target in seen:
                raise CommandError(f"{str(seen[target])!r} and {str(source)!r} would both be "
                                   f"written to {str(target)!r}")
            seen[target] = source
    for source, target in pairs:
        if target.resolve() == source.resolve():
            raise CommandError(f"writing {str(target)!r} would overwrite its input")
    folder.mkdir(parents=True, exist_ok=True)  # the same way for one file or many
    return pairs


def refuse_threshold_flag(args: argparse.Namespace) -> None:
    """Explain the retired ``--threshold`` flag (registered hidden by a subcommand)."""
    if getattr(args, "threshold", None) is not None:
        raise CommandError(
            "--threshold is gone: it meant a contrast threshold for some methods and a firing "
            "threshold for lif; give --set threshold=T (evdown downscale --help lists each "
            "method's settings)"
        )


def _downscale(args: argparse.Namespace) -> int:
    refuse_threshold_flag(args)
    settings = dict(args.set or [])
    unknown = sorted(set(settings) - set(method_settings(args.method)))
    if unknown:  # before reading anything
        raise CommandError(f"method {args.method!r} does not take setting(s) {unknown}; it "
                           f"takes {list(method_settings(args.method))}")
    pairs = _plan(args.paths, args.output_format)
    several = len(pairs) > 1
    torch.set_num_threads(args.threads)
    # Three steps per file (read, downscale, write), so that one long file shows progress too.
    bar = tqdm(total=3 * len(pairs), unit="step", disable=not sys.stderr.isatty(),
               file=sys.stderr, dynamic_ncols=True, leave=False,
               bar_format="{desc} |{bar}| {n_fmt}/{total_fmt} [{elapsed}]")
    for index, (source, target) in enumerate(pairs):
        file_label = f"file {index + 1}/{len(pairs)} {source.name}" if several else source.name
        try:
            bar.set_description_str(f"{file_label}: reading")
            events, sensor_size, unit = read_input(source, args)
            transform = make_method(args.method, sensor_size, args.factor, **settings)
            check_timing(events["t"], time_settings(transform), source=str(source))
            bar.update()
            bar.set_description_str(f"{file_label}: downscaling {len(events)} events")
            start = time.perf_counter()
            out = transform(events)
            seconds = time.perf_counter() - start
            bar.update()
            bar.set_description_str(f"{file_label}: writing")
            written = write_events(target, out, sensor_size=transform.output_sensor_size,
                                   time_unit=unit)
            bar.update()
        except (ValueError, TypeError) as error:
            bar.close()
            raise CommandError(f"{source}: {error}" if several else str(error)) from None
        rate = len(events) / seconds if seconds > 0 else float("inf")
        _say(
            f"{args.method}: {len(events)} events in, {len(out)} events out "
            f"({len(out) / max(len(events), 1):.3f} of the input), sensor {sensor_size} -> "
            f"{transform.output_sensor_size}, {seconds:.4f} s ({rate / 1e6:.2f} M events/s); "
            f"wrote {written}"
        )
    bar.close()
    return 0


def add_downscale_command(commands: argparse._SubParsersAction) -> None:
    """Register ``evdown downscale``."""
    down = commands.add_parser(
        "downscale",
        help="downscale event files (or folders of them) into .npy or HDF5 files",
        description="Downscale event recordings. Inputs: "
        f"{', '.join(READ_EXTENSIONS)} files, or folders of them. With one input file, OUT is "
        "the output file (.npy, .h5 or .hdf5); with several inputs or a folder, OUT is a "
        "folder that gets one file per input, named after it. Missing output folders are "
        "created. Outputs record their sensor size and time unit (HDF5 attributes, or "
        "FILE.npy.json next to a .npy), so that they read back as they were written.",
        epilog=_methods_help(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    down.add_argument("paths", nargs="+", metavar="PATH",
                      help="input files or folders, then the output file or folder")
    down.add_argument("--method", required=True, type=_method, metavar="NAME",
                      help="the method, by name or class name (listed below)")
    down.add_argument("--factor", required=True, type=_factor, help="F or FX,FY")
    down.add_argument("--set", type=_setting, action="append", metavar="KEY=VALUE",
                      help="a setting of the method (listed below), e.g. --set threshold=0.5; "
                      "repeatable")
    add_input_arguments(down)
    down.add_argument("--output-format", choices=("npy", "h5"), default="npy",
                      help="format of the files written into an output folder (default npy)")
    down.add_argument("--threshold", help=argparse.SUPPRESS)  # gone: explains itself
    down.set_defaults(run=_downscale)


# ----------------------------------------------------------------------------- bench, evaluate


def _bench(args: argparse.Namespace) -> int:
    from evdown_torch import bench

    return bench.run_from_args(args)


def add_bench_command(commands: argparse._SubParsersAction) -> None:
    """Register ``evdown bench``."""
    bench = commands.add_parser(
        "bench", help="benchmark every method against its peers; write a report and plots",
        description="Time every downscaling method, and its peers in Tonic, on a synthetic "
        "gesture recording, a large 1280x720 stream and any --input files, at factors 2 to "
        "8, with one torch thread (median of several calls); then sweep events, sensor size "
        "and duration, and measure peak memory in a fresh process. Writes report.md, "
        "results.json and PNG plots to --out; a progress bar per stage on a terminal. "
        "--short takes under 2 minutes; the full run tens of minutes.",
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
    bench.add_argument("--realtime", action="store_true",
                       help="replay a recording (the first --input, else a synthetic gesture "
                       "one) through every streaming session in 1 ms and 10 ms chunks, at its "
                       "own rate and at 25 M events/s; writes realtime.md/.json/.png")
    bench.set_defaults(run=_bench)


def _evaluate(args: argparse.Namespace) -> int:
    from evdown_torch.evaluation.config import load_config
    from evdown_torch.evaluation import markdown_table, run_evaluation, write_report
    from evdown_torch.evaluation.report import primary_table

    try:
        config = load_config(args.config)
        result = run_evaluation(config, cache=not args.no_cache)
    except (OSError, RuntimeError) as error:
        raise CommandError(str(error)) from None
    write_report(result, args.output or config.output.directory,
                 log=lambda line: print(line, file=sys.stderr))
    print(primary_table(result) + "\n" + markdown_table(result), end="")
    return 0


def add_evaluate_command(commands: argparse._SubParsersAction) -> None:
    """Register ``evdown evaluate``."""
    evaluate = commands.add_parser(
        "evaluate",
        help="train and test a spiking classifier on every method and factor; write a report",
        description="Measure each method's speed/accuracy trade: downscale a dataset with "
        "every method and factor of the configuration, train and test a spiking classifier on "
        "each (over several seeds), and write results.csv, report.md and tradeoff.png. The "
        "configuration (TOML, e.g. configs/quick.toml) names the dataset, methods, factors, "
        "training and output folder; recordings, frames and predictions are cached, so a "
        "rerun resumes. Long: configs/quick.toml takes 15 to 40 minutes on a laptop CPU.",
    )
    evaluate.add_argument("--config", required=True, metavar="FILE",
                          help="TOML configuration, e.g. configs/quick.toml")
    evaluate.add_argument("--output", metavar="DIR",
                          help="output directory (default: the config's [output] directory)")
    evaluate.add_argument("--no-cache", action="store_true",
                          help="neither read nor keep the cache of recordings, frames and "
                          "predictions (work in a temporary directory)")
    evaluate.set_defaults(run=_evaluate)


def add_preprocess_command(commands: argparse._SubParsersAction) -> None:
    """Register ``evdown preprocess`` (:mod:`evdown_torch.data.command`)."""
    from evdown_torch.data import command

    command.add_parser(commands)


def add_show_command(commands: argparse._SubParsersAction) -> None:
    """Register ``evdown show`` (:mod:`evdown_torch.plot.cli`)."""
    from evdown_torch.plot.cli import add_parser

    add_parser(commands)


# ----------------------------------------------------------------------------- the program

#: One function per subcommand, in ``--help`` order; each adds its parser and sets ``run``.
SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [
    add_downscale_command,
    add_preprocess_command,
    add_bench_command,
    add_evaluate_command,
    add_show_command,
]


def build_parser() -> argparse.ArgumentParser:
    """The ``evdown`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="evdown", description="Downscale event-camera streams (evdown_torch)."
    )
    parser.add_argument("--version", action="version", version=f"evdown {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add_command in SUBCOMMANDS:
        add_command(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = build_parser().parse_args(argv)
    prefix = f"evdown {args.command}"

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        tqdm.write(f"{prefix}: warning: {message}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.showwarning = show
        try:
            return args.run(args)
        except (CommandError, ValueError, TypeError, ImportError, OSError, EOFError) as error:
            print(f"{prefix}: error: {error}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"{prefix}: interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
