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
  does (see :mod:`evdown_torch.plot.command`).

Each subcommand lives in the package that owns it, as a module with an
``add_command(subparsers)`` that adds its parser and sets ``run`` (a function of the parsed
arguments returning the exit status); :data:`SUBCOMMANDS` lists those modules, and what they
share (:class:`CommandError`, argument types, the input options) is in
:mod:`evdown_torch.arguments`. A run that raises :class:`CommandError`, ``ValueError``,
``TypeError``, ``ImportError``, ``OSError`` or ``EOFError`` (a file that ends too soon) ends
with the one line ``evdown COMMAND: error: ...`` and exit status 2, as argparse does for bad
arguments; warnings print as ``evdown COMMAND: warning:``, in the command line's words where
the warning carries them (its ``command_line`` attribute: ``--time-unit`` where a Python
caller is told ``time_unit=``).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence
from types import ModuleType
from typing import TextIO

from tqdm import tqdm

from evdown_torch import __version__, downscale
from evdown_torch.arguments import CommandError
from evdown_torch.bench import command as bench_command
from evdown_torch.data import command as preprocess_command
from evdown_torch.evaluation import command as evaluate_command
from evdown_torch.plot import command as show_command

__all__ = ["SUBCOMMANDS", "CommandError", "build_parser", "main"]

#: The subcommands' modules, in ``--help`` order; each has ``add_command(subparsers)``.
SUBCOMMANDS: tuple[ModuleType, ...] = (
    downscale,
    preprocess_command,
    bench_command,
    evaluate_command,
    show_command,
)


def build_parser() -> argparse.ArgumentParser:
    """The ``evdown`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="evdown", description="Downscale event-camera streams (evdown_torch)."
    )
    parser.add_argument("--version", action="version", version=f"evdown {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in SUBCOMMANDS:
        module.add_command(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = build_parser().parse_args(argv)
    prefix = f"evdown {args.command}"

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
             file: TextIO | None = None, line: str | None = None) -> None:
        text = getattr(message, "command_line", None) or message
        tqdm.write(f"{prefix}: warning: {text}", file=sys.stderr)

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
