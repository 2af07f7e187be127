"""``evdown downscale``: downscale event files (or folders of them) into ``.npy`` or HDF5 files.

``evdown downscale IN [IN ...] OUT --method NAME --factor F [--set KEY=VALUE ...]`` reads any
format :mod:`evdown_torch.io` reads, runs one method of
:data:`~evdown_torch.transforms.registry.METHODS` on each file and writes the result with its
sensor size and time unit. ``--budget TARGET`` first calibrates the method's budget setting on
all the inputs (:meth:`~evdown_torch.transforms.BudgetTarget.parse`) and records it beside
each output. :func:`add_command` registers it on the ``evdown`` parser.
"""

from __future__ import annotations

import argparse
import os
import sys
import textwrap
import time
import warnings
from collections.abc import Sequence
from dataclasses import MISSING, fields
from pathlib import Path
from typing import NamedTuple, cast

import numpy as np
import torch
from tqdm import tqdm

from evdown_torch.arguments import (
    CommandError,
    Subparsers,
    add_input_arguments,
    check_creatable,
    factor_argument,
    read_input,
    refuse_threshold_flag,
    setting_argument,
)
from evdown_torch.io import (
    READ_EXTENSIONS,
    check_readable,
    check_writable,
    event_files,
    write_events,
)
from evdown_torch.threads import command_threads
from evdown_torch.time_units import check_timing, time_settings
from evdown_torch.transforms import Downscaler
from evdown_torch.transforms.calibrate import BudgetTarget, calibration
from evdown_torch.transforms.registry import METHODS, make_method, method_settings
from evdown_torch.transforms.window_rates import WindowRates

#: Window of the rates printed and recorded for a budget without one (a peak has its own).
RATES_WINDOW_US = 1_000

__all__ = ["add_command"]


def _normal(name: str) -> str:
    return name.lower().replace("_", "").replace("-", "")


def _method(text: str) -> str:
    """A registry name from a registry name or a class name (``event_count``, ``EventCount``)."""
    aliases: dict[str, str] = {}
    for name, cls in METHODS.items():
        aliases[_normal(name)] = name
        aliases[_normal(cls.__name__)] = name
    found = aliases.get(_normal(text))
    if found is None:
        choices = ", ".join(f"{n} ({c.__name__})" for n, c in METHODS.items())
        raise argparse.ArgumentTypeError(f"unknown method {text!r}; choose one of {choices}")
    return found


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
    check_creatable(folder, hint="; several inputs, a folder input or a trailing '/' need an "
                    "output folder" if folder == output else "")
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


class _Budget(NamedTuple):
    """``--budget`` as written and as read."""

    text: str
    target: BudgetTarget


def _budget(text: str) -> _Budget:
    """An argparse type: ``--budget ratio=R | count=N | rate=HZ | peak=HZ/WINDOW``."""
    try:
        return _Budget(text, BudgetTarget.parse(text))
    except (ValueError, TypeError) as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _check_budget(args: argparse.Namespace, settings: dict[str, object]) -> None:
    """Refuse ``--budget`` for a method without a budget setting, or with that setting set."""
    if args.budget is None:
        return
    setting = METHODS[args.method].budget_setting
    if setting is None:
        budgeted = ", ".join(n for n, c in METHODS.items() if c.budget_setting is not None)
        raise CommandError(f"--budget: method {args.method!r} has no budget setting (its "
                           f"output count is fixed by its input); these have one: {budgeted}")
    if setting in settings:
        raise CommandError(f"--budget chooses {setting}: give --budget or --set {setting}=..., "
                           "not both")


def _calibrated(args: argparse.Namespace, settings: dict[str, object],
                inputs: list[tuple[np.ndarray, tuple[int, int, int], str | None]]
                ) -> tuple[Downscaler, dict[str, object]]:
    """The method calibrated to ``--budget`` on every input, and what the sidecar records."""
    sizes = sorted({size for _, size, _ in inputs})
    if len(sizes) > 1:
        raise CommandError(f"--budget calibrates one setting on all the inputs, which must "
                           f"share one sensor size; got {sizes}")
    transform = make_method(args.method, sizes[0], args.factor, **settings)
    budget = cast(_Budget, args.budget)
    window = budget.target.window or RATES_WINDOW_US
    found = calibration(transform, [events for events, _, _ in inputs], budget.target,
                        window=window)
    setting = cast(str, type(transform).budget_setting)
    rates = cast(WindowRates, found.rates)
    total_in = sum(len(events) for events, _, _ in inputs)
    output = (f"peak {found.count} events per window (at most {found.target:g})"
              if budget.target.kind == "peak" else
              f"{rates.events} events, {rates.events / total_in:.4f} of the input "
              f"(target {found.target:.6g} events)")
    _say(f"{args.method}: calibrated {setting}={found.value:.6g} on {len(inputs)} file(s) "
         f"for --budget {budget.text}: {output}; {rates.describe()}")
    if budget.target.kind == "peak" and found.count > found.target:
        warnings.warn(f"no {setting} tried keeps the peak at or under {found.target:g} events "
                      f"per window; the lowest found is {found.count}", stacklevel=2)
    record = {"method": args.method, "budget": budget.text, setting: found.value,
              "rates_per_second": {"window_us": window,
                                   "mean": rates.per_second(rates.mean),
                                   "p99": rates.per_second(rates.p99),
                                   "peak": rates.per_second(rates.peak)}}
    return found.transform, {"calibration": record}


def _downscale(args: argparse.Namespace) -> int:
    refuse_threshold_flag(args)
    settings = dict(args.set or [])
    unknown = sorted(set(settings) - set(method_settings(args.method)))
    if unknown:  # before reading anything
        raise CommandError(f"method {args.method!r} does not take setting(s) {unknown}; it "
                           f"takes {list(method_settings(args.method))}")
    _check_budget(args, settings)
    pairs = _plan(args.paths, args.output_format)
    several = len(pairs) > 1
    torch.set_num_threads(command_threads(args.threads))
    calibrated: Downscaler | None = None
    metadata: dict[str, object] = {}
    inputs: list[tuple[np.ndarray, tuple[int, int, int], str | None]] = []
    if args.budget is not None:  # every input first: the calibration sees them all
        for source, _ in pairs:
            try:
                inputs.append(read_input(source, args))
            except (ValueError, TypeError) as error:
                raise CommandError(f"{source}: {error}" if several else str(error)) from None
        calibrated, metadata = _calibrated(args, settings, inputs)
    # Three steps per file (read, downscale, write), so that one long file shows progress too.
    bar = tqdm(total=3 * len(pairs), unit="step", disable=not sys.stderr.isatty(),
               file=sys.stderr, dynamic_ncols=True, leave=False,
               bar_format="{desc} |{bar}| {n_fmt}/{total_fmt} [{elapsed}]")
    failed: list[Path] = []
    for index, (source, target) in enumerate(pairs):
        file_label = f"file {index + 1}/{len(pairs)} {source.name}" if several else source.name
        steps = bar.n
        try:
            bar.set_description_str(f"{file_label}: reading")
            events, sensor_size, unit = inputs[index] if inputs else read_input(source, args)
            transform = calibrated or make_method(args.method, sensor_size, args.factor,
                                                  **settings)
            check_timing(events["t"], time_settings(transform), source=str(source),
                         transforms=(transform,))
            bar.update()
            bar.set_description_str(f"{file_label}: downscaling {len(events)} events")
            start = time.perf_counter()
            out = cast(np.ndarray, transform(events))  # a structured array in, one out
            seconds = time.perf_counter() - start
            bar.update()
            bar.set_description_str(f"{file_label}: writing")
            written = write_events(target, out, sensor_size=transform.output_sensor_size,
                                   time_unit=unit, metadata=metadata)
            bar.update()
        except (ValueError, TypeError, OSError, EOFError) as error:
            message = f"{source}: {error}" if several else str(error)
            if args.on_error == "stop":
                bar.close()
                left = len(pairs) - index - 1
                raise CommandError(message + (f" ({left} file(s) after it not done; "
                                              "--on-error skip does them)" if left else "")
                                   ) from None
            failed.append(source)
            tqdm.write(f"evdown downscale: error: {message} (skipped)", file=sys.stderr)
            bar.update(steps + 3 - bar.n)
            continue
        rate = len(events) / seconds if seconds > 0 else float("inf")
        _say(
            f"{args.method}: {len(events)} events in, {len(out)} events out "
            f"({len(out) / max(len(events), 1):.3f} of the input), sensor {sensor_size} -> "
            f"{transform.output_sensor_size}, {seconds:.4f} s ({rate / 1e6:.2f} M events/s); "
            f"wrote {written}"
        )
    bar.close()
    if failed:
        print(f"evdown downscale: {len(failed)} of {len(pairs)} files failed (skipped: "
              f"{', '.join(str(f) for f in failed)}); the others were written", file=sys.stderr)
        return 1
    return 0


def add_command(commands: Subparsers) -> None:
    """Register ``evdown downscale`` on the ``evdown`` subparsers."""
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
    down.add_argument("--factor", required=True, type=factor_argument, help="F or FX,FY")
    down.add_argument("--set", type=setting_argument, action="append", metavar="KEY=VALUE",
                      help="a setting of the method (listed below), e.g. --set threshold=0.5; "
                      "repeatable")
    down.add_argument("--budget", type=_budget, metavar="TARGET",
                      help="choose the method's budget setting (threshold, or lif's weight) "
                      "on all the input files together so that the output meets TARGET: "
                      "ratio=R (output events per input event), rate=HZ (mean events per "
                      "second), count=N (events in all) or peak=HZ/WINDOW (at most HZ events "
                      "per second in every window, e.g. peak=500000/1ms: 500 events in any "
                      "1 ms). Prints the setting and the mean, p99 and peak rates, and records "
                      "them in each output's sidecar (HDF5: attribute 'calibration'); reads "
                      "every input before writing any output")
    add_input_arguments(down)
    down.add_argument("--output-format", choices=("npy", "h5"), default="npy",
                      help="format of the files written into an output folder (default npy)")
    down.add_argument("--on-error", choices=("stop", "skip"), default="stop",
                      help="a file that cannot be read or downscaled: stop there (default), or "
                      "report it, skip it and do the others (exit status 1 if any failed)")
    down.add_argument("--threshold", help=argparse.SUPPRESS)  # gone: explains itself
    down.set_defaults(run=_downscale)
