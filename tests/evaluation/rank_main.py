"""One rank of the tests' ``torchrun`` launches of ``evdown``, with changes for some ranks.

    torchrun ... tests/evaluation/rank_main.py [OPTION ...] evaluate --config FILE ...

Options (before the ``evdown`` arguments; the rank is torchrun's ``RANK``):

``--private-cache``
    every rank keeps its cache in a folder of its own (``CACHE/rank-R``), as ranks on machines
    without a shared file system do;
``--exit-after-training R``
    rank ``R`` exits at once (status 3, no clean-up, as a killed process would) when its first
    training job (not a learning-rate run) has finished and stored its result;
``--config-of R FILE``
    rank ``R`` reads ``FILE`` instead of the command's ``--config``.

The package has no hook for any of this: the changes are made here, to this process only.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

from evdown_torch.cli import main
from evdown_torch.evaluation import classifier
from evdown_torch.evaluation import config as config_module


def _private_cache(rank: int) -> None:
    load = config_module.load_config

    def private(path, overrides=()):
        config = load(path, overrides)
        cache = str(Path(config.output.cache) / f"rank-{rank}")
        return dataclasses.replace(config, output=dataclasses.replace(config.output, cache=cache))

    config_module.load_config = private


def _exit_after_training() -> None:
    train = classifier.train_job

    def train_then_exit(*args, **kwargs):
        out = train(*args, **kwargs)
        validation = args[7] if len(args) > 7 else kwargs.get("validation", False)
        if not validation:
            os._exit(3)
        return out

    classifier.train_job = train_then_exit


def run(argv: list[str]) -> int:
    rank = int(os.environ["RANK"])
    while argv and argv[0].startswith("--"):
        option = argv.pop(0)
        if option == "--private-cache":
            _private_cache(rank)
        elif option == "--exit-after-training":
            if int(argv.pop(0)) == rank:
                _exit_after_training()
        elif option == "--config-of":
            who, path = int(argv.pop(0)), argv.pop(0)
            if who == rank:
                argv[argv.index("--config") + 1] = path
        else:
            raise SystemExit(f"rank_main.py: unknown option {option}")
    return main(argv)


if __name__ == "__main__":
    sys.exit(run(sys.argv[1:]))
