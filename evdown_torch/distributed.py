"""The ranks of a ``torchrun`` launch: who is who, the process group, and sharing out work.

``evdown preprocess`` and ``evdown evaluate`` run as the ranks of a ``torchrun`` launch (one
process per rank, on one machine or many). Their command lines join the process group torchrun
describes with :func:`process_group` (gloo: only small Python objects travel, on any machine,
with or without GPUs); the library calls then read :func:`rank_and_world` and meet through the
collectives below, which are plain calls in a single process. :func:`folder_groups` finds which
ranks see the same folder (a shared file system), and :func:`balance` shares jobs of known
expected cost out among ranks.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path
from typing import Any, TypeVar

__all__ = [
    "TIMEOUT",
    "all_gather",
    "balance",
    "barrier",
    "broadcast",
    "folder_groups",
    "local_rank",
    "process_group",
    "rank_and_world",
]

T = TypeVar("T")

#: How long a rank waits for the others at a collective. A stage of a study (every rank's
#: share of the training) can last days on a few ranks. A rank that dies ends the launch sooner:
#: torchrun stops the other ranks when one fails.
TIMEOUT = timedelta(days=7)


def rank_and_world() -> tuple[int, int]:
    """``(rank, world size)`` in the initialised ``torch.distributed`` process group.

    ``(0, 1)`` without one.
    """
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def local_rank() -> int:
    """This rank's number on its machine (torchrun's ``LOCAL_RANK``; 0 without torchrun)."""
    return int(os.environ.get("LOCAL_RANK", "0"))


@contextmanager
def process_group() -> Iterator[None]:
    """Join the gloo process group torchrun describes for the ``with`` block, and leave it.

    Nothing happens outside a ``torchrun`` launch or where a group is already initialised
    (by the caller, who then also ends it).
    """
    import torch.distributed as dist

    launched = dist.is_available() and dist.is_torchelastic_launched()
    joined = launched and not dist.is_initialized()
    if joined:
        dist.init_process_group("gloo", timeout=TIMEOUT)
    try:
        yield
    except BaseException:
        if joined and dist.is_initialized():
            dist.destroy_process_group()
        raise
    if joined and dist.is_initialized():
        # Every rank leaves together: a rank that tears its gloo connections down while a
        # peer still holds them can be aborted ("terminate called without an active
        # exception"), seen once in the two-rank test.
        dist.barrier()
        dist.destroy_process_group()


def all_gather(value: T) -> list[T]:
    """Every rank's ``value``, in rank order (``[value]`` in a single process)."""
    import torch.distributed as dist

    if rank_and_world()[1] == 1:
        return [value]
    gathered: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(gathered, value)
    return gathered


def broadcast(value: T, source: int = 0) -> T:
    """Rank ``source``'s ``value``, on every rank (``value`` itself in a single process)."""
    import torch.distributed as dist

    if rank_and_world()[1] == 1:
        return value
    box: list[Any] = [value]
    dist.broadcast_object_list(box, src=source)
    return box[0]


def barrier() -> None:
    """Wait until every rank gets here (nothing in a single process)."""
    import torch.distributed as dist

    if rank_and_world()[1] > 1:
        dist.barrier()


def folder_groups(folder: str | Path) -> list[tuple[int, ...]]:
    """The ranks that see one and the same ``folder``, as groups in rank order.

    Each rank writes a probe file named by a token of rank 0 and its rank into its own
    ``folder`` (created if absent); after a barrier each rank looks for every rank's probe. Ranks
    that see the same probes share the folder (a shared file system, or one machine); a rank
    that sees only its own keeps its folder to itself. Where the answers do not form groups
    (one rank sees another's probe but not the other way round), every rank is taken to be
    alone, which is always safe: ranks that share a folder without knowing it only write the
    same bytes twice. A collective: every rank must call it.

    Returns:
        ``[(0, 1, ...)]`` where every rank shares the folder; ``[(0,), (1,), ...]`` where none
        does; ``[(0,)]`` in a single process.
    """
    rank, world = rank_and_world()
    if world == 1:
        return [(0,)]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    token = broadcast(secrets.token_hex(8))
    probes = [folder / f".evdown-probe-{token}-{r}" for r in range(world)]
    probes[rank].touch()
    try:
        barrier()
        seen = all_gather(tuple(r for r in range(world) if probes[r].is_file()))
        barrier()
    finally:
        probes[rank].unlink(missing_ok=True)
    groups = sorted(set(seen))
    consistent = all(r in seen[r] and all(seen[s] == seen[r] for s in seen[r])
                     for r in range(world))
    return groups if consistent else [(r,) for r in range(world)]


def balance(costs: Sequence[float], capacity: Sequence[float]) -> list[int]:
    """Share jobs of expected ``costs`` out among bins of ``capacity`` (ranks: 1 each).

    The longest job first, each to the bin that would finish it soonest (its load plus the
    job, divided by its capacity; ties to the first bin): Graham's LPT rule, within 4/3 of the
    best makespan on equal bins. Deterministic, so every rank computes the same plan.

    Returns:
        The bin of each job.

    Example:
        >>> balance([3, 3, 2, 2, 2], [1, 1])
        [0, 1, 0, 1, 0]
        >>> balance([4, 1, 1, 1, 1], [2, 1])  # a bin of two ranks: 6 against 2
        [0, 1, 1, 0, 0]
    """
    load = [0.0] * len(capacity)
    bins = [0] * len(costs)
    for job in sorted(range(len(costs)), key=lambda j: -costs[j]):
        best = min(range(len(capacity)),
                   key=lambda b: (load[b] + costs[job]) / capacity[b])
        bins[job] = best
        load[best] += costs[job]
    return bins
