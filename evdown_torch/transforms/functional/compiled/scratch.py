"""Scratch columns that a thread reuses from call to call, when nothing else holds them.

A live session calls the compiled kernels on a chunk every few milliseconds, and each call
used to take new columns for the chunk's fields (:func:`~.columns.read_columns`) and for the
crossings found (:func:`~.regions.crossing_columns`). Columns of a few megabytes come from
the operating system fresh each time, and their first writes fault in zeroed pages: on the
live replay's chunks (300,000 events), in a process that had freed no large block before, that
cost EventCount a quarter to two fifths of its chunk (docs/benchmarks.md, "Second session of
2026-12-03"). Here each thread keeps the last column it took for each *slot* and hands the
same memory out again, **only where no other object still refers to it** (a view, a tensor
made with ``torch.from_numpy``, an ``Events`` that kept a column, a method's state):
CPython's reference count says so, so a column still in use is never overwritten, and a new
one is taken instead.

Columns over :data:`LARGEST_KEPT` bytes are not kept, nor a column that would take the
thread's kept columns past :data:`MOST_KEPT` bytes in all: a thread holds at most that much
after its calls, however many slots its methods use, until it ends or calls
:func:`release_scratch`. Python builds without the GIL (whose reference counts are not exact
from another thread) take new columns every time.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Iterator

import numpy as np

__all__ = [
    "LARGEST_KEPT",
    "MOST_KEPT",
    "kept_bytes",
    "kept_map",
    "release_scratch",
    "scratch_column",
    "scratch_copy",
]

#: The largest column (bytes) a thread keeps for reuse: 8 MiB (a million int64 values).
LARGEST_KEPT = 8 << 20

#: The most a thread keeps in all its columns (bytes): 160 MiB. A column that would take it
#: past this is new and not kept (the slot keeps its last column).
MOST_KEPT = 160 << 20

#: References to a kept column while no one else holds it: the thread's table, the name
#: ``kept`` in :func:`scratch_column` and ``sys.getrefcount``'s own argument.
_UNUSED_REFERENCES = 3

_EXACT_REFERENCES = getattr(sys, "_is_gil_enabled", lambda: True)()


class _Kept(threading.local):
    """Each thread's kept columns, by ``(slot, dtype)``."""

    def __init__(self) -> None:
        self.columns: dict[tuple[str, np.dtype], np.ndarray] = {}


_KEPT = _Kept()


def scratch_column(slot: str, n: int, dtype: np.dtype | type) -> np.ndarray:
    """An uninitialised ``(n,)`` column, the memory of this thread's last one for ``slot``.

    The memory is reused only where nothing else refers to the slot's last column (nor to
    any view of it) and it is long enough; else the column is new, and kept in its place.
    Columns over :data:`LARGEST_KEPT` bytes are new and not kept. The caller must not let
    the column outlive the call unless it hands it on as an object that refers to it (a
    view, a tensor made with ``torch.from_numpy``): that reference is what keeps the next
    call from reusing it. A column handed on is a view of the kept one, which may be longer
    (up to :data:`LARGEST_KEPT` bytes stay alive behind it). A new column that would take
    the thread's kept columns past :data:`MOST_KEPT` bytes is not kept.

    Args:
        slot: the column's use (one name per column a call holds at once).
        n: its length.
        dtype: its NumPy dtype.

    Returns:
        A view of ``n`` elements (of a kept column as long or longer).

    Example:
        >>> a = scratch_column("doctest", 1000, np.int64)
        >>> b = scratch_column("doctest", 1000, np.int64)  # ``a`` is alive: new memory
        >>> bool(np.shares_memory(a, b))
        False
        >>> address = b.__array_interface__["data"][0]
        >>> del a, b
        >>> c = scratch_column("doctest", 800, np.int64)  # ``b``'s, which no one holds now
        >>> c.__array_interface__["data"][0] == address
        True
    """
    dtype = np.dtype(dtype)
    size = n * dtype.itemsize
    if size > LARGEST_KEPT or not _EXACT_REFERENCES:
        return np.empty(n, dtype)
    key = (slot, dtype)
    kept = _KEPT.columns.get(key)
    if (kept is not None and kept.shape[0] >= n
            and sys.getrefcount(kept) == _UNUSED_REFERENCES):
        return kept[:n]
    replaced = 0 if kept is None else kept.nbytes
    if kept_bytes() - replaced + size > MOST_KEPT:
        return np.empty(n, dtype)  # (the slot keeps its last column)
    kept = np.empty(n, dtype)
    _KEPT.columns[key] = kept
    return kept[:n]


@contextlib.contextmanager
def kept_map(slot: str, n: int, dtype: np.dtype | type) -> Iterator[np.ndarray]:
    """A ``(n,)`` map that this thread keeps from call to call, as the last call left it.

    For a per-pixel map that a loop touches at a chunk's pixels only: taking new memory (or
    zeroing it) every call would cost the sensor's area a call, not the chunk's events.
    A new map is zeros; a kept one holds what the last ``with`` body of ``slot`` left in it,
    so the body restores what its own rule needs (zeros where it wrote, say) before it ends.
    The map is the body's alone: it leaves the table for the body's time (a nested use of
    ``slot`` gets a new one), and a body that raises loses it (the next call's is zeros).
    The body must not let the map or a view of it outlive the ``with``.

    Kept whatever its size, while the thread's kept columns stay within :data:`MOST_KEPT`
    bytes in all; another ``n`` or dtype takes a new map (the slot keeps the last one).
    :func:`release_scratch` lets go of the maps too.

    Args:
        slot: the map's use.
        n: its length.
        dtype: its NumPy dtype.

    Example:
        >>> with kept_map("doctest map", 4, np.int64) as seen:
        ...     seen[2] = 7  # the body's rule here: leave the count of calls in seen[0]
        ...     seen[0] += 1
        >>> with kept_map("doctest map", 4, np.int64) as seen:
        ...     seen.tolist()
        [1, 0, 7, 0]
    """
    dtype = np.dtype(dtype)
    key = (f"map {slot}", dtype)
    kept = _KEPT.columns.pop(key, None)
    mapped = kept if kept is not None and kept.shape[0] == n else np.zeros(n, dtype)
    yield mapped
    if kept_bytes() + mapped.nbytes <= MOST_KEPT:
        _KEPT.columns[key] = mapped
    elif kept is not None and kept is not mapped:
        _KEPT.columns[key] = kept  # (what the slot kept before, unchanged)


def kept_bytes() -> int:
    """The bytes this thread keeps in its scratch columns (at most :data:`MOST_KEPT`).

    Example:
        >>> before = kept_bytes()
        >>> column = scratch_column("doctest kept bytes", 1000, np.int64)  # a new slot
        >>> kept_bytes() - before
        8000
    """
    return sum(column.nbytes for column in _KEPT.columns.values())


def release_scratch() -> int:
    """Let go of the scratch columns the calling thread keeps for the compiled kernels.

    A thread that ran compiled kernels on the CPU keeps up to ``MOST_KEPT`` bytes
    (160 MiB) of columns for its next calls, until it ends. A process done with its live
    session or its preprocessing, that goes on with other work in the same thread, calls this
    to give that memory back. Nothing in use is touched: a column something still refers to
    (an output tensor, an ``Events``, a session's state) stays valid and is freed when its last
    holder lets go; the thread's next compiled call takes new columns. Other threads' columns
    are theirs to release.

    Returns:
        The bytes the thread kept (``kept_bytes()`` before the call; the memory of columns
        still held elsewhere is freed later, when they are).

    Example:
        >>> import evdown_torch, torch
        >>> count = evdown_torch.EventCount((4, 4, 2), factor=2, threshold=0.5)
        >>> out = count(torch.tensor([[0, 0, 10, 1], [1, 1, 20, 1]]))
        >>> released = evdown_torch.release_scratch()  # what the call kept, if compiled
        >>> kept_bytes(), out.tolist()  # nothing kept; the output is intact
        (0, [[0, 0, 20, 1]])
    """
    released = kept_bytes()
    _KEPT.columns.clear()
    return released


def scratch_copy(slot: str, values: np.ndarray) -> np.ndarray:
    """A copy of the 1-D ``values`` in the scratch column of ``slot`` (:func:`scratch_column`).

    Example:
        >>> scratch_copy("doctest copy", np.arange(3)).tolist()
        [0, 1, 2]
    """
    copy = scratch_column(slot, values.shape[0], values.dtype)
    copy[:] = values
    return copy
