"""What every ``evdown`` subcommand shares: its error type, argument types and input options.

Each subcommand lives in the package that owns it (:mod:`evdown_torch.downscale`,
:mod:`evdown_torch.data.command`, :mod:`evdown_torch.bench.command`,
:mod:`evdown_torch.evaluation.command`, :mod:`evdown_torch.plot.command`) and registers itself
through its ``add_command(subparsers)``; :mod:`evdown_torch.cli` only collects them. They take
their common pieces from here, so that no subcommand imports the command line back.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from evdown_torch._text import parse_factor, parse_setting
from evdown_torch.io import check_columns, read_microseconds
from evdown_torch.threads import check_threads
from evdown_torch.time_units import TIME_UNITS, timing_checked_by_caller

__all__ = [
    "CommandError",
    "Subparsers",
    "add_file_format_options",
    "add_input_arguments",
    "add_out_option",
    "add_sensor_size_option",
    "add_threads_option",
    "check_creatable",
    "factor_argument",
    "read_input",
    "refuse_threshold_flag",
    "setting_argument",
]

#: The object ``ArgumentParser.add_subparsers`` returns, which each ``add_command`` receives.
Subparsers = argparse._SubParsersAction


class CommandError(Exception):
    """A problem with the command's input, reported as one line without a traceback."""


def check_creatable(folder: Path, what: str = "", hint: str = "") -> None:
    """Refuse a ``folder`` that cannot be made because a file stands at or above it.

    Args:
        folder: the folder a command will create (or that exists).
        what: what the folder is, for the message (``"output folder"``).
        hint: said after the message when the file is ``folder`` itself.

    Raises:
        CommandError: ``cannot create [what] 'folder': 'file' is a file``.
    """
    for above in (folder, *folder.parents):  # the folder, and its missing parents
        if above.exists() and not above.is_dir():
            name = f"the {what} {str(folder)!r}" if what else repr(str(folder))
            raise CommandError(f"cannot create {name}: {str(above)!r} is a file"
                               + (hint if above == folder else ""))


def factor_argument(text: str) -> int | tuple[int, int]:
    """An argparse type: a factor, ``F`` or ``FX,FY`` (positive integers)."""
    try:
        return parse_factor(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def setting_argument(text: str) -> tuple[str, object]:
    """An argparse type: one ``KEY=VALUE`` setting, the value read as a Python literal."""
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
        raise argparse.ArgumentTypeError(
            f"--threads must be a positive integer, got {text!r}") from None
    try:
        return check_threads(value, "--threads")
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def add_sensor_size_option(parser: argparse.ArgumentParser, help: str) -> None:
    """Add ``--sensor-size W H P`` (three integers) with its own ``help``."""
    parser.add_argument("--sensor-size", type=int, nargs=3, metavar=("W", "H", "P"), help=help)


def add_out_option(parser: argparse.ArgumentParser, help: str) -> None:
    """Add the required ``--out DIR``, the folder a command writes into, with its own ``help``."""
    parser.add_argument("--out", required=True, metavar="DIR", help=help)


def add_threads_option(parser: argparse.ArgumentParser, help: str) -> None:
    """Add ``--threads N`` with its own ``help``.

    A positive integer of at most :data:`~evdown_torch.threads.MAX_THREADS`; ``None`` when
    not given, which :func:`~evdown_torch.threads.command_threads` resolves at run time
    (``OMP_NUM_THREADS`` where set, else 1).
    """
    parser.add_argument("--threads", type=_threads, metavar="N",
                        help=f"{help}; default: OMP_NUM_THREADS where set, else 1")


def add_file_format_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--time-unit`` and ``--columns``, what a file may not say about itself.

    :func:`read_input` (or :func:`evdown_torch.io.read_microseconds` with ``args.time_unit``
    and ``args.columns``) reads files as they say.
    """
    parser.add_argument("--time-unit", choices=tuple(TIME_UNITS), metavar="UNIT",
                        help="unit of the input timestamps (s, ms, us, ns) for files that do "
                        "not state one (camera formats are us; a file's own unit wins); "
                        "timestamps are converted to microseconds, the unit of every time "
                        "setting (dt, tau, max_delay). Default: us")
    parser.add_argument("--columns", type=_columns, metavar="A,B,C,D",
                        help="column order of .npy files holding an (N, 4) array, e.g. "
                        "t,x,y,p (default x,y,t,p)")


def add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options that say how to read input files and how many threads to use.

    They are ``--sensor-size``, ``--time-unit``, ``--columns`` (:func:`add_file_format_options`)
    and ``--threads``.
    """
    add_sensor_size_option(parser, "input sensor size for files that do not record one (.npy "
                           "without a sidecar, .bin, some .raw/.dat/HDF5); a file's own size "
                           "wins, so one value serves a mixed folder; else it is guessed with "
                           "a warning")
    add_file_format_options(parser)
    add_threads_option(parser, "torch threads (one is never much slower, often faster on a busy "
                       "machine; see docs/benchmarks.md)")


def read_input(
    path: Path, args: argparse.Namespace
) -> tuple[np.ndarray, tuple[int, int, int], str | None]:
    """Read an input file as the options of :func:`add_input_arguments` say.

    Through :func:`evdown_torch.io.read_microseconds`, whose timing check is left to the
    caller (:func:`~evdown_torch.time_units.timing_checked_by_caller`): the command checks
    the file against its settings.

    Returns:
        ``(events, sensor_size, time_unit)``: a structured event array with ``t`` in
        microseconds where the unit is known (``time_unit`` ``"us"``, else ``None``).
    """
    with timing_checked_by_caller():
        recording = read_microseconds(
            path, sensor_size=args.sensor_size, time_unit=args.time_unit,
            **({"columns": args.columns} if args.columns else {}))
    return recording.events, recording.sensor_size, recording.time_unit


def refuse_threshold_flag(args: argparse.Namespace) -> None:
    """Explain the retired ``--threshold`` flag (registered hidden by a subcommand)."""
    if getattr(args, "threshold", None) is not None:
        raise CommandError(
            "--threshold is gone: it meant a contrast threshold for some methods and a firing "
            "threshold for lif; give --set threshold=T (evdown downscale --help lists each "
            "method's settings)"
        )
