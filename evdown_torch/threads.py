"""Threads: torch's thread count, set for a while and put back, and guards against misuse.

Every kernel here is vectorised torch code; on the small tensors of one recording, torch's
intra-op threads cost more in hand-over than they save, and on a busy machine they wait for
cores (``docs/benchmarks.md``, "Threads"). The command line and the dataset preprocessing
therefore run one thread per process by default (``OMP_NUM_THREADS``, when set, is the
command line's default instead); library calls leave the caller's setting alone, except inside
:func:`torch_threads`. A thread count is a positive integer of at most :data:`MAX_THREADS`
(:func:`check_threads`).

:class:`OneCallAtATime` refuses a second call into an object that is not thread-safe (a
streaming session) while a first one runs, instead of letting two calls mix its state.
"""

from __future__ import annotations

import os
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch

from evdown_torch.checks import check_positive_int

__all__ = [
    "MAX_THREADS",
    "OneCallAtATime",
    "available_cores",
    "check_threads",
    "command_threads",
    "torch_threads",
]

#: The most torch threads a process may be given. It is more than the cores of any machine this
#: package runs on, and few enough for OpenMP to start them (tens of thousands exhaust its
#: memory; beyond int64 torch cannot even take the number).
MAX_THREADS = 1024


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return max(len(os.sched_getaffinity(0)), 1)
    return max(os.cpu_count() or 1, 1)


def check_threads(threads: Any, name: str = "threads") -> int:
    """Validate a torch thread count: a positive integer of at most :data:`MAX_THREADS`.

    Raises:
        TypeError, ValueError: naming ``name``, the rule and the value.

    Example:
        >>> check_threads(4)
        4
    """
    threads = check_positive_int(name, threads)
    if threads > MAX_THREADS:
        raise ValueError(
            f"{name} must be at most {MAX_THREADS} (this machine has {available_cores()} "
            f"cores), got {threads}"
        )
    return threads


def command_threads(given: int | None) -> int:
    """The torch threads of an ``evdown`` command.

    ``--threads`` where given, else ``OMP_NUM_THREADS`` where set (its first number, as
    OpenMP reads it), else 1. Warns when the count exceeds the cores available (the threads
    would wait for each other), and when ``OMP_NUM_THREADS`` is not a valid count (1 is used).

    Args:
        given: the ``--threads`` value (checked by :func:`check_threads`), or ``None``.

    Returns:
        The thread count to use.
    """
    if given is not None:
        threads = check_threads(given, "--threads")
        source = f"--threads {threads}"
    else:
        text = os.environ.get("OMP_NUM_THREADS", "").strip()
        if not text:
            return 1
        try:
            threads = check_threads(int(text.split(",")[0]), "OMP_NUM_THREADS")
        except ValueError:
            warnings.warn(f"OMP_NUM_THREADS={text!r} is not a thread count (a positive integer "
                          f"of at most {MAX_THREADS}); using 1 thread", stacklevel=2)
            return 1
        source = f"OMP_NUM_THREADS={text}"
    cores = available_cores()
    if threads > cores:
        warnings.warn(
            f"{source} asks for more threads than the {cores} cores available here: the "
            "threads wait for each other and run slower than one per core",
            stacklevel=2,
        )
    return threads


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the ``with`` block with ``torch.set_num_threads(threads)``, then restore the count.

    Raises:
        ValueError: unless ``threads`` is a positive integer of at most :data:`MAX_THREADS`.

    Example:
        >>> import torch
        >>> before = torch.get_num_threads()
        >>> with torch_threads(1):
        ...     torch.get_num_threads()
        1
        >>> torch.get_num_threads() == before
        True
    """
    threads = check_threads(threads)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class OneCallAtATime:
    """A guard that lets one call in at a time and refuses any other at once.

    ``with guard:`` around each public call of an object that is not thread-safe: a call
    made while another one is inside (from another thread) raises a ``RuntimeError`` at once,
    before touching anything, instead of mixing two calls' state. A copy of the object
    (``copy.deepcopy``, pickling) gets a guard of its own, free.

    Args:
        what: what the object is, for the message (``"session"``).
        advice: what to do instead, for the message.

    Example:
        >>> guard = OneCallAtATime("session", "give each thread its own")
        >>> with guard:
        ...     try:
        ...         with guard:  # a second call while the first one runs
        ...             pass
        ...     except RuntimeError as error:
        ...         print(str(error)[:32])
        this session is already in use b
    """

    def __init__(self, what: str, advice: str) -> None:
        self.what, self.advice = what, advice
        self._lock = threading.Lock()

    def __enter__(self) -> None:
        if not self._lock.acquire(blocking=False):
            raise RuntimeError(
                f"this {self.what} is already in use by a call that has not returned (another "
                f"thread): it takes one call at a time; {self.advice}"
            )

    def __exit__(self, *exc_info: object) -> None:
        self._lock.release()

    def __getstate__(self) -> dict[str, str]:
        return {"what": self.what, "advice": self.advice}

    def __setstate__(self, state: dict[str, str]) -> None:
        self.__init__(**state)  # type: ignore[misc]
