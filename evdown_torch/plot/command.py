"""``evdown show``: see what each method does (:func:`add_command` registers it).

``evdown show IN --factor F [--methods a,b,...] [--window MS] [--out FILE.gif|FILE.png]``
writes a side-by-side animation (GIF) or a contact sheet (PNG); with ``--curve X,Y`` it writes
the paper's Figure 5 for output pixel ``(X, Y)`` instead. ``IN`` is an event file (any format
of :mod:`evdown_torch.io`), ``synthetic:CLASS[:SEED]`` or ``nmnist:DIGIT[:N]`` with ``--root``
(see :func:`~evdown_torch.plot.recording.load_recording`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import torch

from evdown_torch._regions import region_of
from evdown_torch.arguments import (
    CommandError,
    Subparsers,
    add_input_arguments,
    factor_argument,
    setting_argument,
)
from evdown_torch.checks import check_factor, output_size
from evdown_torch.events import Events
from evdown_torch.plot._mpl import MissingMatplotlib
from evdown_torch.plot.recording import SYNTHETIC_DURATION_MS, load_recording, method_name
from evdown_torch.threads import command_threads
from evdown_torch.time_units import check_timing, time_settings, timing_checked_by_caller
from evdown_torch.transforms import Downscaler, ThresholdDownscaler
from evdown_torch.transforms.registry import METHODS, make_method, method_settings

DEFAULT_ANIMATION = "evdown_show.gif"
DEFAULT_CURVE = "evdown_curve.png"


def _methods(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in METHODS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(
            f"methods must be a comma-separated list of {', '.join(METHODS)}, got {text!r}"
        )
    return names


def _pixel(text: str) -> tuple[int, int]:
    parts = text.split(",")
    try:
        x, y = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"the pixel must be X,Y (two integers), got {text!r}"
        ) from None
    return x, y


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def add_command(subparsers: Subparsers) -> None:
    """Register ``evdown show`` on the ``evdown`` subparsers."""
    show = subparsers.add_parser(
        "show", help="see what each method does: an animation, a contact sheet or a pixel's curves",
        description="Draw a recording next to its downscaled versions (GIF animation, or PNG "
        "contact sheet when --out ends in .png), or with --curve X,Y the levels, "
        "reconstructions, thresholds and events of one output pixel (the paper's Figure 5).",
    )
    show.add_argument("input", metavar="IN",
                      help="an event file (.npy, .h5, .aedat4, .bin, .raw, .dat; t in "
                      "microseconds unless the file or --time-unit says otherwise), "
                      "synthetic:CLASS[:SEED] (a synthetic gesture, class index or name) or "
                      "nmnist:DIGIT[:N] (the N-th recording of a digit of the N-MNIST folder "
                      "--root)")
    show.add_argument("--factor", required=True, type=factor_argument, help="F or FX,FY")
    show.add_argument("--methods", type=_methods, metavar="A,B,...",
                      help=f"methods to show (default: all of {', '.join(METHODS)})")
    show.add_argument("--window", type=_positive, default=50.0, metavar="MS",
                      help="frame length in milliseconds (default 50)")
    show.add_argument("--out", metavar="FILE",
                      help=f".gif (animation) or .png (contact sheet); with --curve any image "
                      f"format matplotlib writes (default {DEFAULT_ANIMATION} / {DEFAULT_CURVE})")
    show.add_argument("--curve", type=_pixel, metavar="X,Y",
                      help="draw output pixel X,Y's levels, reconstructions and events instead")
    show.add_argument("--threshold", type=_positive, metavar="T",
                      help="contrast threshold of event_count, linear and cubic (default 1)")
    show.add_argument("--set", type=setting_argument, action="append", metavar="[NAME.]KEY=VALUE",
                      help="a setting for every chosen method that takes KEY, or for method "
                      "NAME only, e.g. --set lif.weight=0.5")
    add_input_arguments(show)  # --sensor-size (synthetic default 128 128 2), --time-unit, ...
    show.add_argument("--duration", type=_positive, metavar="MS",
                      help=f"synthetic recording length (default {SYNTHETIC_DURATION_MS:g}); "
                      "for a file, show only its first MS milliseconds")
    show.add_argument("--windows", type=int, default=4, metavar="N",
                      help="windows on a contact sheet (default 4)")
    show.add_argument("--root", metavar="DIR",
                      help="the N-MNIST folder of an nmnist: input (Train/<digit>/*.bin and "
                      "Test/...)")
    show.add_argument("--split", choices=("train", "test"), default="train",
                      help="the N-MNIST split of an nmnist: input (default train)")
    show.add_argument("--no-ground-truth", action="store_true",
                      help="leave out the low-resolution ground truth of a synthetic input")
    show.set_defaults(run=run)


def build_transforms(
    names: list[str] | None,
    sensor_size: tuple[int, int, int],
    factor: int | tuple[int, int],
    threshold: float | None,
    settings: list[tuple[str, Any]],
) -> list[Downscaler]:
    """The chosen methods with ``--threshold`` and ``--set`` applied.

    ``threshold`` goes to the contrast-threshold methods (event_count, linear, cubic); a
    setting ``KEY`` to every chosen method that takes it (an error when none does), a setting
    ``NAME.KEY`` to method ``NAME`` only.
    """
    names = list(METHODS) if names is None else names
    per_method: dict[str, dict[str, Any]] = {name: {} for name in names}
    if threshold is not None:
        for name in names:
            if issubclass(METHODS[name], ThresholdDownscaler):
                per_method[name]["threshold"] = threshold
    for key, value in settings:
        target, dot, setting = key.partition(".")
        if dot:
            if target not in per_method:
                raise ValueError(
                    f"--set {key}: {target!r} is not one of the chosen methods {names}"
                )
            per_method[target][setting] = value
            continue
        takers = [name for name in names if key in method_settings(name)]
        if not takers:
            raise ValueError(f"--set {key}: none of the chosen methods {names} takes {key!r}")
        for name in takers:
            per_method[name][key] = value
    return [make_method(name, sensor_size, factor, **per_method[name]) for name in names]


def busiest_pixel(
    events: Events, factor: int | tuple[int, int], sensor_size: tuple[int, int, int]
) -> tuple[int, int, int]:
    """The output pixel whose region has the most input events: ``(X, Y, count)``."""
    fx, fy = check_factor(factor, sensor_size)
    out_w, out_h, _ = output_size(sensor_size, (fx, fy))
    rx, ry = region_of(events, (fx, fy))
    region = ry * out_w + rx
    counts = torch.bincount(region, minlength=out_w * out_h)
    best = int(counts.argmax())
    return best % out_w, best // out_w, int(counts[best])


def _progress(frame: int, total: int) -> None:
    if sys.stderr.isatty():
        end = "\n" if frame + 1 == total else ""
        print(f"\revdown show: frame {frame + 1}/{total}", end=end, file=sys.stderr, flush=True)


def _log(line: str) -> None:
    print(f"evdown show: {line}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    """Run ``evdown show`` from parsed arguments; returns the exit status."""
    if args.windows < 1:
        raise CommandError(f"--windows must be a positive integer, got {args.windows}")
    try:
        return _run(args)
    except MissingMatplotlib as error:
        raise CommandError(str(error)) from None
    except OSError as error:
        raise CommandError(f"cannot write {error.filename or args.out!r}: "
                           f"{error.strerror or error}") from None


def _run(args: argparse.Namespace) -> int:
    from evdown_torch.plot import _mpl, animation, curve
    from evdown_torch.plot.recording import panels

    _mpl.matplotlib()  # before any work: its absence is reported up front
    default = DEFAULT_CURVE if args.curve else DEFAULT_ANIMATION
    out = Path(args.out or default)
    suffix = out.suffix.lower()
    if not args.curve and suffix not in (".gif", ".png"):
        raise ValueError(f"--out must end in .gif (animation) or .png (contact sheet), "
                         f"got {str(out)!r}")
    if args.curve and suffix in ("", ".gif"):
        raise ValueError(f"--out for --curve must be an image such as .png, .svg or .pdf, "
                         f"got {str(out)!r}")
    torch.set_num_threads(command_threads(args.threads))
    sensor = tuple(args.sensor_size) if args.sensor_size else None
    with timing_checked_by_caller():  # checked below, against every setting
        recording = load_recording(args.input, sensor_size=sensor, duration_ms=args.duration,
                                   time_unit=args.time_unit, columns=args.columns,
                                   root=args.root, split=args.split)
    transforms = build_transforms(args.methods, recording.sensor_size, args.factor,
                                  args.threshold, args.set or [])
    settings = {f"{method_name(t)}.{key}": value
                for t in transforms for key, value in time_settings(t).items()}
    if not args.curve:
        settings["--window"] = 1000.0 * args.window
    check_timing(recording.events.t, settings, source=recording.name, transforms=transforms)
    truth = None if args.no_ground_truth else recording.ground_truth(args.factor)
    if args.curve:
        curves = curve.region_curves(recording.events, recording.sensor_size, args.factor,
                                     args.curve, transforms,
                                     ground_truth=None if truth is None else truth.events)
        figure = curve.curve_figure(curves)
        figure.savefig(out)
        x, y, count = busiest_pixel(recording.events, args.factor, recording.sensor_size)
        print(f"wrote {out}: output pixel {args.curve} of {recording.name}, "
              f"{len(transforms)} methods (the busiest output pixel is ({x}, {y}), "
              f"with {count} input events)")
        return 0
    shown = panels(recording.events, recording.sensor_size, args.factor, transforms,
                   ground_truth=truth, log=_log)
    if suffix == ".png":
        figure = animation.contact_sheet(shown, window_ms=args.window, windows=args.windows)
        figure.savefig(out)
        rows = len(figure.axes) // len(shown)
        print(f"wrote {out}: {rows} windows of {args.window:g} ms x {len(shown)} panels")
        return 0
    movie = animation.animate(shown, window_ms=args.window)
    frames = animation.frame_grid(shown, args.window).count
    animation.save(movie, str(out), progress=_progress)
    print(f"wrote {out}: {frames} frames of {args.window:g} ms x {len(shown)} panels")
    return 0
