"""The study over the ranks of a ``torchrun`` launch (docs/evaluation.md, "On a cluster").

Every stage of :func:`~evdown_torch.evaluation.study.run_evaluation` is a list of jobs, and
every rank computes the same placement of them (:func:`evdown_torch.distributed.balance`, by
the expected costs below), runs its own through its worker processes, and meets the others at
the stage's end. Ranks that see the same cache folder form a group
(:func:`evdown_torch.distributed.folder_groups`):

* **One group** (a shared file system, or one machine): any rank can read what any other made,
  so each job goes to one rank. Each job stores its result in the cache before it returns and
  only reads it when it is there, so after the stage every rank reads the others' results from
  the shared cache (per-seed predictions, calibrations, stream measures) by asking the job
  again (a result not yet visible there, as behind an NFS client's cache, is made again: the
  same result, at the cost of the job).
* **Several groups** (each machine its own disk): recordings and frames do not travel. Every
  group makes the recordings and the camera's renders itself; each cell belongs to one group
  (chosen by the cells' expected cost), which makes its frames, runs its learning-rate
  selection if it is a factor's selection cell, and trains all its seeds. The results of every
  job travel through the process group (gloo).

Per-seed results do not depend on the rank that made them (the jobs are deterministic functions
of their settings), so the report is the same as one process's. Without ``torch.distributed``
there is one rank and everything runs as it always did.

The costs are rough seconds of one CPU thread: the method speeds of docs/benchmarks.md (128x128
gestures at factor 4) and the quick run's framing and training times. Only their ratios matter.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evdown_torch.distributed import (
    all_gather,
    balance,
    barrier,
    folder_groups,
    rank_and_world,
)
from evdown_torch.evaluation.cache import Cache
from evdown_torch.evaluation.cells import BASELINE, CONTROL, TONIC, Cell
from evdown_torch.evaluation.classifier import model_for, trained_with
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.plan import Planned

__all__ = [
    "EVERY_GROUP",
    "Ranks",
    "Stage",
    "check_agreement",
    "claim_cache",
    "cell_groups",
    "downscale_seconds",
    "release",
    "seed_recordings",
    "study_settings",
    "training_seconds",
]

#: ``where`` of a stage whose every job each group of ranks makes for itself.
EVERY_GROUP = "every group"

#: Milliseconds of one thread per million input events (docs/benchmarks.md, "gesture", factor 4;
#: the control is Downsample and a random draw per event).
METHOD_MS = {"downsample": 7.5, "funnelling": 24.4, "event_count": 20.3, "linear": 111.0,
             "cubic": 289.0, "lif": 222.0, "photocurrent": 54.1, TONIC: 1196.0, CONTROL: 15.0,
             BASELINE: 0.0}
#: Framing and measuring one cell's output, milliseconds per million input events (the quick
#: run: 160 CPU seconds for 53 cells and draws of 462 recordings).
FRAMING_MS = 13.0
#: Input events per second of recording at 128x128 (the quick run's: 135,000 in 3 s).
EVENTS_PER_SECOND = 45_000.0
#: The classifier's multiply-accumulates per second of one thread, counting a training pass
#: as three (the quick run: 3.6 s per seed at x4, 21.3 MMACs per recording).
MACS_PER_SECOND = 3.7e10
#: Recordings' length where the config crops none (DVS128 Gesture's last about 6 s), us.
DEFAULT_DURATION_US = 6_000_000


def _events_per_recording(config: EvaluationConfig) -> float:
    width, height, _ = config.data.full_sensor_size
    seconds = (config.data.duration_us or DEFAULT_DURATION_US) / 1e6
    return EVENTS_PER_SECOND * seconds * width * height / 128**2


def downscale_seconds(config: EvaluationConfig, cells: Sequence[Cell], recordings: int) -> float:
    """Expected time to downscale ``recordings`` recordings into each of ``cells``' frames.

    Example:
        >>> from evdown_torch.evaluation.config import parse_config
        >>> config = parse_config({"data": {"sensor_size": [128, 128], "duration_us": 1_000_000}})
        >>> round(downscale_seconds(config, [Cell("cubic", (4, 4), 1.0)], 1000), 1)
        13.6
    """
    events = _events_per_recording(config) * recordings
    return events * sum(METHOD_MS.get(c.method, METHOD_MS["cubic"]) + FRAMING_MS
                        for c in cells) / 1e9


def training_seconds(config: EvaluationConfig, cell: Cell, train: int, test: int) -> float:
    """Expected time to train ``cell``'s classifier on ``train`` recordings and test ``test``.

    Example:
        >>> from evdown_torch.evaluation.config import parse_config
        >>> config = parse_config({"data": {"time_bins": 12, "mean_time": True}, "model": {
        ...     "channels": [16, 32], "pool_size": 4, "grid": 32, "stem_channels": 8},
        ...     "training": {"epochs": 15}})
        >>> round(training_seconds(config, Cell("event_count", (4, 4), 1.0), 132, 264), 1)
        3.6
    """
    config = trained_with(config, cell)
    w, h, _ = cell.output_size(config.data.full_sensor_size)
    macs = model_for(config, (w, h), 11).macs_per_step(h, w) * config.data.time_bins
    return macs * (3 * train * config.training.epochs + test) / MACS_PER_SECOND


@dataclass(frozen=True)
class Stage:
    """What a stage gave: each job's result, in order, and the jobs this rank ran.

    Attributes:
        results: one per job; ``None`` for another rank's job where the stage's results were
            not gathered.
        here: the jobs (indices) this rank ran.
    """

    results: list[Any]
    here: list[int]


class Ranks:
    """This process's place among the ranks, and the placement and gathering of jobs.

    Args:
        folder: the cache folder, to find which ranks share it (a collective: every rank
            calls this). Without ``torch.distributed``: one rank.

    Attributes:
        rank, world: this rank and the number of ranks.
        groups: the ranks that share a cache folder, by group.
        group: the group of this rank.
        jobs: how many jobs this rank has run so far.
    """

    def __init__(self, folder: str | Path) -> None:
        self.rank, self.world = rank_and_world()
        self.groups = folder_groups(folder)
        self.group = next(i for i, g in enumerate(self.groups) if self.rank in g)
        self.jobs = 0

    @property
    def through_cache(self) -> bool:
        """Whether results are read from the shared cache (one group), not sent."""
        return len(self.groups) == 1

    @property
    def gathered_through(self) -> str:
        """How the results reach the ranks, in words (empty for one process)."""
        if self.world == 1:
            return ""
        return "the shared cache folder" if self.through_cache else "the process group"

    def describe(self) -> str:
        """The ranks and how they share the work, for the log."""
        if self.through_cache:
            return (f"{self.world} ranks share the cache folder: each job runs on one rank, "
                    "and results are read from the cache")
        return (f"{self.world} ranks in {len(self.groups)} groups sharing a cache folder "
                f"({', '.join('+'.join(map(str, g)) for g in self.groups)}): each group makes "
                "its own recordings and the frames of its cells; results travel through the "
                "process group")

    def cell_groups(self, costs: Sequence[float]) -> list[int]:
        """The group of each cell, by the cells' expected ``costs`` (larger groups take more)."""
        return balance(costs, [len(g) for g in self.groups])

    def runners(self, costs: Sequence[float], where: Sequence[int] | str | None = None
                ) -> list[tuple[int, ...]]:
        """The ranks that run each job of a stage.

        Args:
            costs: each job's expected cost.
            where: ``None``: any one rank; :data:`EVERY_GROUP`: one rank of every group; else
                the group of each job (one of its ranks runs it).
        """
        if self.world == 1:
            return [(0,)] * len(costs)
        if where is None:
            return [(r,) for r in balance(costs, [1.0] * self.world)]
        runners: list[tuple[int, ...]] = [()] * len(costs)
        for g, members in enumerate(self.groups):
            jobs = [j for j in range(len(costs)) if where == EVERY_GROUP
                    or (not isinstance(where, str) and where[j] == g)]
            for j, b in zip(jobs, balance([costs[j] for j in jobs], [1.0] * len(members))):
                runners[j] += (members[b],)
        return runners

    def gather(self, fn: Callable, columns: Sequence[Sequence[Any]],
               runners: list[tuple[int, ...]], mine: dict[int, Any], needed: bool = True
               ) -> list[Any]:
        """Every job's result on every rank, once every rank has run its jobs (``mine``).

        One group reads the others' results from the shared cache (``fn`` again, which finds
        them there); several groups send them through the process group, each rank taking a
        job's result from a rank of its own group where one ran it. With ``needed=False`` the
        ranks only wait for each other, and other ranks' results are ``None``.
        """
        if self.world == 1:
            return [mine[j] for j in range(len(runners))]
        barrier()
        if not needed:
            return [mine.get(j) for j in range(len(runners))]
        if self.through_cache:
            return [mine[j] if j in mine else fn(*(column[j] for column in columns))
                    for j in range(len(runners))]
        every = all_gather(mine)
        mates = set(self.groups[self.group])
        return [every[next((r for r in ranks if r in mates), ranks[0])][j]
                for j, ranks in enumerate(runners)]


# ----------------------------------------------------------------------- the same config


def study_settings(config: EvaluationConfig) -> dict[str, Any]:
    """Every setting the study depends on, flat (``"training.epochs": 15``), as JSON reads it.

    ``[output]`` (places, not the study) and the name are left out.

    Example:
        >>> from evdown_torch.evaluation.config import parse_config
        >>> flat = study_settings(parse_config({"settings": {"lif": {"dt": 500}}}))
        >>> flat["training.epochs"], flat["settings.lif.dt"], "output.cache" in flat
        (10, 500, False)
    """
    flat: dict[str, Any] = {}
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value) and field.name != "output":
            for key, item in dataclasses.asdict(value).items():  # type: ignore[arg-type]
                flat[f"{field.name}.{key}"] = item
    for method, settings in config.settings.items():
        for key, item in settings.items():
            flat[f"settings.{method}.{key}"] = item
    return json.loads(json.dumps(flat, sort_keys=True, default=str))


def _differing(a: dict[str, Any], b: dict[str, Any]) -> str:
    keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    return ", ".join(keys[:5]) + (f" and {len(keys) - 5} more" if len(keys) > 5 else "")


def check_agreement(config: EvaluationConfig) -> None:
    """Refuse to start where the ranks hold different configs (a different file on one node).

    Each rank sends a SHA-256 of :func:`study_settings`; where they differ, the settings
    themselves, to name what differs. A collective: every rank must call it, before any work.

    Raises:
        ValueError: on every rank, naming the ranks and settings that differ from rank 0's.
    """
    settings = study_settings(config)
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()
    digests = all_gather(digest)
    if len(set(digests)) == 1:
        return
    every = all_gather(settings)
    differ = [f"rank {r} in {_differing(every[0], every[r])}"
              for r in range(len(every)) if digests[r] != digests[0]]
    raise ValueError(
        "the ranks disagree on the config (compared by a hash of its settings, [output] "
        f"aside): {'; '.join(differ)} differ from rank 0; give every rank the same file")


def claim_cache(store: Cache, config: EvaluationConfig, ranks: Ranks) -> Path | None:
    """Refuse a config that differs from an unfinished distributed run's in the same cache.

    A run under ``torchrun`` records its settings in ``CACHE/runs/NAME.json`` (``NAME``: the
    config's name) until it finishes; a later run of a study of that name with other settings
    is refused (one or many ranks), so that a rerun after a fault finishes the run that was
    started. Runs that finish remove the record (:func:`release`); a single process writes
    none, so without ``torchrun`` nothing is ever refused. A collective.

    Returns:
        The record's path (``None`` for a temporary cache).

    Raises:
        ValueError: on every rank, where any rank's cache holds another config's record.
    """
    if store.temporary:
        return None
    path = store.root / "runs" / f"{config.name}.json"
    settings = study_settings(config)
    problem = None
    if path.is_file():
        try:
            previous = Cache.load_json(path).get("settings")
        except (OSError, ValueError, AttributeError):
            previous = None
        if previous != settings:
            differs = _differing(previous, settings) if isinstance(previous, dict) else \
                "an unreadable record"
            problem = (f"the cache {str(store.root)!r} holds an unfinished run of study "
                       f"{config.name!r} with another configuration (differs in {differs}); "
                       f"rerun that configuration to finish it, or delete {str(path)!r} to "
                       "start this one")
    problems = [p for p in all_gather(problem) if p is not None]
    if problems:
        raise ValueError(problems[0])
    if ranks.world > 1 and ranks.rank == ranks.groups[ranks.group][0]:
        store.save_json(path, {"settings": settings, "ranks": ranks.world})
    return path


def release(record: Path | None) -> None:
    """Remove a run's record once it has finished (see :func:`claim_cache`)."""
    if record is not None:
        record.unlink(missing_ok=True)


def seed_recordings(config: EvaluationConfig, pool: int, validation: bool = False) -> int:
    """How many of a ``pool`` of training recordings one seed trains on.

    As :func:`~evdown_torch.evaluation.classifier.draw_training_set` draws them.
    """
    pool -= config.data.validation_samples if validation else 0
    return min(config.data.train_per_seed or pool, pool)


def cell_groups(config: EvaluationConfig, ranks: Ranks, planned: Sequence[Planned],
                selection: dict[tuple[int, int], Cell], train: int, test: int
                ) -> dict[Cell, int]:
    """The group of ranks that makes each cell's frames and trains it, by its expected time.

    A cell's time: its frames (every draw, ``train + test`` recordings), its seeds' trainings
    and, for a factor's ``selection`` cell, the learning-rate runs. One group: all 0.
    """
    training = config.training
    runs = len(training.learning_rates) * training.selection_seeds
    validation = config.data.validation_samples if runs else 0
    costs = []
    for p in planned:
        draws = len(p.seeds) if p.cell.random else 1
        cost = (downscale_seconds(config, [p.cell] * draws, train + test)
                + len(p.seeds) * training_seconds(config, p.cell, seed_recordings(config, train),
                                                  test))
        if runs and selection.get(p.cell.factor) == p.cell:
            cost += runs * training_seconds(config, p.cell, seed_recordings(config, train, True),
                                            validation)
        costs.append(cost)
    return dict(zip((p.cell for p in planned), ranks.cell_groups(costs)))
