"""``evdown evaluate``: the study's command line (see docs/evaluation.md).

``evdown evaluate --config FILE [--set TABLE.KEY=VALUE ...] [--output DIR] [--no-cache]`` runs
:func:`~evdown_torch.evaluation.study.run_evaluation` on a TOML configuration
(:mod:`evdown_torch.evaluation.config`) and writes ``results.csv``, ``report.md`` and
``tradeoff.png``. :func:`add_command` registers it on the ``evdown`` parser. Under
``torchrun`` each rank runs the command: they share the study's jobs and rank 0 writes the
report (docs/evaluation.md, "On a cluster").
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from evdown_torch.arguments import CommandError, Subparsers, check_creatable

__all__ = ["add_command"]


def _evaluate(args: argparse.Namespace) -> int:
    from evdown_torch.distributed import process_group, rank_and_world
    from evdown_torch.evaluation.config import load_config
    from evdown_torch.evaluation.report import markdown_table, primary_table, write_report
    from evdown_torch.evaluation.study import run_evaluation

    with process_group():  # one rank of a torchrun launch joins the others
        try:
            config = load_config(args.config, args.set or ())
        except (OSError, RuntimeError) as error:
            raise CommandError(str(error)) from None
        output = Path(args.output or config.output.directory)
        # Every folder the study writes, checked before any work (the study takes minutes).
        check_creatable(output, "output folder")
        if not args.no_cache:
            check_creatable(Path(config.output.cache), "cache folder")
        # The folder is made with the report (after the ranks agree on the config); the
        # nearest existing folder must take it.
        existing = next(f for f in (output, *output.parents) if f.exists())
        if not os.access(existing, os.W_OK | os.X_OK):
            raise CommandError(f"cannot write the output folder {str(output)!r} into "
                               f"{str(existing)!r}")
        try:
            result = run_evaluation(config, cache=not args.no_cache)
        except (OSError, RuntimeError) as error:
            raise CommandError(str(error)) from None
        if rank_and_world()[0] != 0:
            return 0
    write_report(result, output, log=lambda line: print(line, file=sys.stderr))
    print(primary_table(result) + "\n" + markdown_table(result), end="")
    return 0


def add_command(commands: Subparsers) -> None:
    """Register ``evdown evaluate`` on the ``evdown`` subparsers."""
    evaluate = commands.add_parser(
        "evaluate",
        help="train and test a spiking classifier on every method and factor; write a report",
        description="Measure each method's speed/accuracy trade: downscale a dataset with "
        "every cell of the configuration, train and test a spiking classifier on each (over "
        "several seeds), test the primary family stated in the configuration against the "
        "thinning control, and write results.csv, report.md and tradeoff.png. The "
        "configuration (TOML, e.g. configs/quick.toml) names the dataset, methods, factors, "
        "training and output folder; recordings, frames and predictions are cached, so a "
        "rerun resumes. configs/quick.toml takes about 11 minutes on an idle 2-core machine, "
        "with a progress bar per stage. Under torchrun the ranks (on one machine or many) "
        "share the jobs and rank 0 writes the report.",
    )
    evaluate.add_argument("--config", required=True, metavar="FILE",
                          help="TOML configuration, e.g. configs/quick.toml")
    evaluate.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE",
                          help="replace one setting of the configuration, the value written "
                          "as in TOML (repeatable), e.g. --set data.seed=1 to replicate a "
                          "study on other data")
    evaluate.add_argument("--output", metavar="DIR",
                          help="output directory (default: the config's [output] directory)")
    evaluate.add_argument("--no-cache", action="store_true",
                          help="neither read nor keep the cache of recordings, frames and "
                          "predictions (work in a temporary directory)")
    evaluate.set_defaults(run=_evaluate)
