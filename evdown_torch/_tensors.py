"""Small tensor helpers shared by the whole package (private).

Every helper here exists once: time ordering and chunking of a stream, run starts and ends,
segmented sums, distinct values, fast indexing, integer division, small-key stable sorting
and a correctly rounded square root.
The region geometry of a downscaling factor is :mod:`evdown_torch._regions`.
"""

from __future__ import annotations

import contextlib
import threading
import weakref
from collections.abc import Iterator

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "CHUNK_EVENTS",
    "NUMPY_MIN_ELEMENTS",
    "NUMPY_ON_CPU",
    "changes",
    "chunk_bounds",
    "continued_cumsum",
    "correctly_rounded_sqrt",
    "differences",
    "distinct_in_range",
    "divide",
    "ends",
    "floor_divide_exact",
    "last_of_runs",
    "narrow_dtype",
    "note_time_order",
    "run_index",
    "run_max",
    "runs_of",
    "searchsorted_ascending",
    "segmented_cumsum",
    "stable_sort_small",
    "take",
    "telescoped_cumsum",
    "time_order",
    "time_order_notes",
    "where_true",
]

#: Events per chunk when a kernel processes a long stream piece by piece: temporaries of this
#: length stay small enough (8 MB of int64) to be recycled by the allocator instead of being
#: mapped afresh, which costs more than the arithmetic on them.
CHUNK_EVENTS = 1 << 20


#: CPU tensors take NumPy's primitive where it is several times faster than this torch
#: build's (:func:`where_true`, :func:`changes`, :func:`runs_of`, :func:`run_max`,
#: :func:`divide`, :func:`searchsorted_ascending`, and :func:`stable_sort_small` for short
#: keys); ``False`` runs torch's everywhere, as on other devices (the tests run both). Below
#: :data:`NUMPY_MIN_ELEMENTS` torch's call costs no more (short sorts excepted).
NUMPY_ON_CPU = True

#: Fewest elements for which the helpers above take NumPy's primitive (measured on this
#: build: from about 1,000 NumPy's is as fast or faster; below, its extra Python calls and
#: conversions cost up to half a microsecond more a call).
NUMPY_MIN_ELEMENTS = 1 << 10


def _numpy(tensor: Tensor) -> bool:
    return (NUMPY_ON_CPU and tensor.device.type == "cpu" and tensor.numel() >= NUMPY_MIN_ELEMENTS
            and tensor.dtype != torch.bfloat16)  # (the one CPU dtype NumPy has no type for)


# --- Rounding -----------------------------------------------------------------------------


def correctly_rounded_sqrt(values: Tensor) -> Tensor:
    """``sqrt(values)`` rounded to the nearest float, as IEEE 754 defines it (a new tensor).

    torch's CPU ``sqrt`` is not: torch 2.13.0's CPU wheel rounds 1.4 % of random float64
    values one unit off, whatever its CPU capability (AVX-512, AVX2 or none), even for one
    value alone; the compiled loops' ``sqrt`` is the CPU's instruction, correctly rounded. A
    kernel whose compiled twin must give the same bits (CubicEstimation's derivative roots)
    takes this one: NumPy's ``sqrt`` on the CPU (the instruction), torch's elsewhere (CUDA
    documents its float64 ``sqrt`` as correctly rounded). Negative values give NaN, without a
    warning.

    Example:
        >>> correctly_rounded_sqrt(torch.tensor([6.167086359879541, 4.0, -1.0],
        ...                                     dtype=torch.float64)).tolist()
        [2.483361906746486, 2.0, nan]
    """
    if values.device.type != "cpu" or values.dtype == torch.bfloat16:
        return torch.sqrt(values)
    with np.errstate(invalid="ignore"):
        return torch.from_numpy(np.sqrt(values.detach().numpy()))


# --- Indexing -----------------------------------------------------------------------------


def take(values: Tensor, index: Tensor) -> Tensor:
    """``values[index]`` for a 1-D int64 ``index`` (``index_select``: much faster on the CPU)."""
    return values.index_select(0, index)


def where_true(mask: Tensor) -> Tensor:
    """``(M,)`` int64 positions of the True entries of a 1-D bool ``mask``, ascending.

    On the CPU through NumPy's ``nonzero`` (reading the mask in place): 4 to 12 times
    faster than ``torch.nonzero`` there on 250k entries, which counts the entries in one pass
    and writes them in a second (docs/benchmarks.md, "Fourth session of 2026-11-27"). The
    kernels call it a few dozen times per chunk.

    Example:
        >>> where_true(torch.tensor([False, True, True, False, True])).tolist()
        [1, 2, 4]
    """
    if _numpy(mask):
        return torch.from_numpy(mask.numpy().nonzero()[0].astype(np.int64, copy=False))
    return torch.nonzero(mask).squeeze(1)


def searchsorted_ascending(ordered: Tensor, keys: Tensor, *, right: bool = False) -> Tensor:
    """``torch.searchsorted(ordered, keys, right=right)`` for ascending ``keys``.

    On the CPU through NumPy's, which starts each search from the previous key's place when
    the keys ascend: about 2x torch's there (300k keys in 400k).

    Example:
        >>> searchsorted_ascending(torch.tensor([1, 3, 3, 7]), torch.tensor([0, 3, 8]),
        ...                        right=True).tolist()
        [0, 3, 4]
    """
    if _numpy(keys) and ordered.device.type == "cpu":
        return torch.from_numpy(np.searchsorted(ordered.numpy(), keys.numpy(),
                                                side="right" if right else "left"))
    return torch.searchsorted(ordered, keys, right=right)


# --- Runs of equal values ------------------------------------------------------------------


def changes(values: Tensor) -> Tensor:
    """``(N,)`` bool run starts: True where ``values`` differs from its predecessor (and at 0).

    Example:
        >>> changes(torch.tensor([3, 3, 5, 5, 3])).tolist()
        [True, False, True, False, True]
    """
    flags = torch.ones(values.shape[0], dtype=torch.bool, device=values.device)
    if _numpy(values):  # NumPy's comparison: about 2x torch's on the CPU (262k int64 values)
        plain = values.numpy()
        np.not_equal(plain[1:], plain[:-1], out=flags.numpy()[1:])
    else:
        torch.ne(values[1:], values[:-1], out=flags[1:])
    return flags


def ends(starts: Tensor) -> Tensor:
    """``(N,)`` bool: True at the last element of each run, given the runs' ``starts``."""
    flags = torch.ones_like(starts)
    flags[:-1] = starts[1:]
    return flags


def last_of_runs(first_at: Tensor, n: int) -> Tensor:
    """``(R,)`` int64 last position of each run, from the runs' first positions ``first_at``.

    The runs cover ``n`` elements one after another (no search for the ends).

    Example:
        >>> last_of_runs(torch.tensor([0, 2, 3]), 6).tolist()
        [1, 2, 5]
    """
    last = torch.empty_like(first_at)
    torch.sub(first_at[1:], 1, out=last[:-1])
    if last.shape[0]:
        last[-1] = n - 1
    return last


def distinct_in_range(values: Tensor, low: int, high: int) -> tuple[Tensor, Tensor]:
    """``torch.unique(values, return_inverse=True)`` of int64 ``values`` in ``low .. high``.

    By a table of one mark a value of the range (its cumulative sum ranks them), not a sort:
    the cheaper where the range is small next to the values; the caller decides that. The
    distinct values are read from the table where it is no longer than the values, else put
    in place by their ranks.

    Returns:
        ``(distinct, inverse)``: the sorted distinct values, and each value's int64 index in
        them.

    Example:
        >>> distinct_in_range(torch.tensor([7, 3, 7, 5]), 3, 7)
        (tensor([3, 5, 7]), tensor([2, 0, 2, 1]))
    """
    offset = values - low
    marked = torch.zeros(high - low + 1, dtype=torch.bool, device=values.device)
    if _numpy(offset):  # NumPy's assignment: a few times torch's on the CPU
        marked.numpy()[offset.numpy()] = True
    else:
        marked[offset] = True
    rank_dtype = torch.int32 if high - low < 1 << 31 else torch.int64  # (half the table)
    rank = torch.cumsum(marked, 0, dtype=rank_dtype)  # marks up to each value of the range
    inverse = take(rank, offset).to(torch.int64).sub_(1)
    if marked.shape[0] <= values.shape[0]:
        return where_true(marked).add_(low), inverse
    distinct = torch.empty(int(rank[-1]), dtype=torch.int64, device=values.device)
    if _numpy(values):
        distinct.numpy()[inverse.numpy()] = values.numpy()
    else:
        distinct[inverse] = values
    return distinct, inverse


def run_index(starts: Tensor) -> Tensor:
    """``(N,)`` int64 index of the run each element belongs to, given the runs' ``starts``."""
    return torch.cumsum(starts.to(torch.int64), 0) - 1


def runs_of(lengths: Tensor, n: int) -> Tensor:
    """``(N,)`` int64 index of the run each element belongs to, from the runs' ``lengths``.

    ``lengths``: ``(R,)`` int64, summing to ``n``. On the CPU through NumPy's ``repeat``
    (about 3x ``torch.repeat_interleave`` there on 262k elements in 1,000 runs).

    Example:
        >>> runs_of(torch.tensor([2, 1, 3]), 6).tolist()
        [0, 0, 1, 2, 2, 2]
    """
    if NUMPY_ON_CPU and lengths.device.type == "cpu" and n >= NUMPY_MIN_ELEMENTS:
        return torch.from_numpy(np.repeat(np.arange(lengths.shape[0], dtype=np.int64),
                                          lengths.numpy()))
    return torch.repeat_interleave(torch.arange(lengths.shape[0], device=lengths.device),
                                   lengths, output_size=n)


def run_max(values: Tensor, first_at: Tensor) -> Tensor:
    """``(R,)`` largest of ``values`` in each run (runs one after another, none empty).

    ``first_at``: ``(R,)`` int64 first position of each run, ascending, the first 0. On the
    CPU through NumPy's ``maximum.reduceat`` (about 13x ``scatter_reduce`` there on 262k
    elements in 1,000 runs); exact for integers.

    Example:
        >>> run_max(torch.tensor([3, 1, 4, 1, 5, 9, 2]), torch.tensor([0, 2, 5])).tolist()
        [3, 5, 9]
    """
    if _numpy(values):
        return torch.from_numpy(np.maximum.reduceat(values.numpy(), first_at.numpy()))
    lengths = torch.diff(first_at, append=first_at.new_tensor([values.shape[0]]))
    run = runs_of(lengths, values.shape[0])
    lowest = torch.finfo(values.dtype).min if values.is_floating_point() else (
        torch.iinfo(values.dtype).min)
    return torch.full((first_at.shape[0],), lowest, dtype=values.dtype,
                      device=values.device).scatter_reduce_(0, run, values, "amax")


def differences(values: Tensor, starts_at: Tensor) -> Tensor:
    """Each element minus its predecessor, except at run starts, where the element itself.

    Args:
        values: ``(N,)`` values.
        starts_at: int64 positions of the runs' first elements (0 among them).

    Example:
        >>> differences(torch.tensor([1, 3, 6, 2, 2]), torch.tensor([0, 3])).tolist()
        [1, 2, 3, 2, 0]
    """
    change = values.clone()
    change[1:] -= values[:-1]
    change.scatter_(0, starts_at, take(values, starts_at))
    return change


def segmented_cumsum(values: Tensor, starts_at: Tensor, segment: Tensor) -> Tensor:
    """Cumulative sum of ``values`` restarting at each segment's start.

    Args:
        values: ``(N,)`` values.
        starts_at: ``(S,)`` int64 start of each segment, ascending, the first 0.
        segment: ``(N,)`` int64 segment of each element.
    """
    total = torch.cumsum(values, 0)
    return total - take(take(total - values, starts_at), segment)


def continued_cumsum(
    change: Tensor, starts: Tensor, lasts: Tensor, initial: Tensor
) -> tuple[Tensor, Tensor]:
    """Each group's running sum of ``change``, from the group's ``initial`` value.

    Groups are contiguous runs of ``change`` (``(N,)``; ``starts`` and ``lasts`` ``(G,)``
    their first and last positions, ``initial`` ``(G,)`` of ``change``'s dtype, overwritten).
    One cumulative sum serves all groups: each group's first change also moves the sum from
    the previous group's last value to this group's ``initial`` (a telescoping correction).
    ``change`` is overwritten with the running sums.

    Returns:
        ``(running, final)``: ``(N,)`` the value after each change (``change`` itself) and
        ``(G,)`` each group's last value.

    Example:
        >>> change = torch.tensor([1, 1, -1, 1, -1])
        >>> running, final = continued_cumsum(change, torch.tensor([0, 2]), torch.tensor([1, 4]),
        ...                                   torch.tensor([5, -3]))
        >>> running.tolist(), final.tolist()
        ([6, 7, -4, -3, -4], [7, -4])
    """
    plain = torch.cumsum(change, 0, dtype=change.dtype)
    final = take(plain, lasts) - take(plain, starts) + take(change, starts) + initial
    del plain
    return telescoped_cumsum(change, starts, initial, final), final


def telescoped_cumsum(change: Tensor, starts: Tensor, initial: Tensor, final: Tensor) -> Tensor:
    """:func:`continued_cumsum`'s running sums when each group's ``final`` value is known.

    Each group's first change also moves the one cumulative sum from the previous group's
    ``final`` to this group's ``initial``; ``change`` and ``initial`` are overwritten.

    Example:
        >>> telescoped_cumsum(torch.tensor([1, 1, -1, 1, -1]), torch.tensor([0, 2]),
        ...                   torch.tensor([5, -3]), torch.tensor([7, -4])).tolist()
        [6, 7, -4, -3, -4]
    """
    jump = initial
    jump[1:] -= final[:-1]
    return change.index_add_(0, starts, jump).cumsum_(0)


# --- Time order and chunks -----------------------------------------------------------------


#: The timestamps last found in time order on their way in, per thread (:func:`note_time_order`).
_NOTED = threading.local()


@contextlib.contextmanager
def time_order_notes() -> Iterator[None]:
    """The span in which :func:`note_time_order`'s notes are taken: one transform's call.

    Outside every such span a note is not taken, and a span's end drops the thread's note,
    so no note outlives the call that took it (nor reaches code of the user's that could
    change the tensor behind torch's back, through a NumPy view).
    """
    _NOTED.depth = getattr(_NOTED, "depth", 0) + 1
    try:
        yield
    finally:
        _NOTED.depth -= 1
        if not _NOTED.depth:
            _NOTED.tensor = None


def note_time_order(t: Tensor) -> None:
    """Remember that ``t`` is in time order, so that :func:`time_order` need not look again.

    For a fact learnt on the way in (the compiled read of a structured array checks the order
    as it copies ``t``: a whole call's kernel then skips a pass over the timestamps, about
    0.5 ms of a 1M-event call). Taken inside :func:`time_order_notes` only. Holds this
    tensor object only, as it is now: a weak reference (no memory kept) and its version
    counter, so a view, a copy or a change in place through torch is looked at again. One
    tensor a thread, the last noted. An inference tensor (``torch.inference_mode``) keeps no
    version counter: it is not noted.
    """
    if not getattr(_NOTED, "depth", 0) or t.is_inference():
        return
    _NOTED.tensor = weakref.ref(t)
    _NOTED.version = t._version


def _noted_in_order(t: Tensor) -> bool:
    """Whether ``t`` is the tensor :func:`note_time_order` noted last, unchanged since."""
    noted = getattr(_NOTED, "tensor", None)
    return noted is not None and noted() is t and t._version == _NOTED.version


def time_order(t: Tensor) -> Tensor | None:
    """Stable permutation that sorts ``t``, or ``None`` when ``t`` is already sorted.

    Args:
        t: ``(N,)`` timestamps.

    Returns:
        ``(N,)`` int64 indices (ties keep input order), or ``None`` for a sorted input (or
        one :func:`note_time_order` noted, unchanged since).
    """
    if t.shape[0] < 2 or _noted_in_order(t):
        return None
    if _numpy(t):  # NumPy's comparison and all(): about 2.5x torch's on a CPU stream
        values = t.detach().numpy()
        if bool(np.all(values[1:] >= values[:-1])):
            return None
    elif bool((t[1:] >= t[:-1]).all()):
        return None
    return torch.sort(t, stable=True).indices


def chunk_bounds(t: Tensor, chunk: int | None = None, *, split_ties: bool = True) -> list[int]:
    """Start indices of consecutive chunks of about ``chunk`` events of a time-sorted stream.

    Args:
        t: ``(N,)`` sorted timestamps.
        chunk: target chunk length (default :data:`CHUNK_EVENTS`).
        split_ties: when False, a chunk never splits a run of equal timestamps.

    Returns:
        ``[0, b1, ..., N]``, strictly increasing (``[0, N]`` for short streams).
    """
    n = t.shape[0]
    chunk = CHUNK_EVENTS if chunk is None else chunk
    if n <= chunk:
        return [0, n]
    starts = torch.arange(chunk, n, chunk, device=t.device)
    if not split_ties:
        starts = torch.searchsorted(t, t[starts], side="left")
    return sorted({0, n, *starts.tolist()})


#: Shortest key tensor that torch's CPU sort orders by radix sort (``at::internal::GRAIN_SIZE``);
#: shorter ones go through a comparison sort, about 15 times slower per key.
RADIX_SORT_MIN = 1 << 15

#: torch's CPU sort has that radix sort (FBGEMM's, accelerated with OpenMP) in this build.
RADIX_SORT = ("fbgemm" in torch.backends.quantized.supported_engines
              and torch.backends.openmp.is_available())

#: Shortest key tensor worth padding to :data:`RADIX_SORT_MIN` keys (measured on this build:
#: from 8,192 keys the padded radix sort beats the comparison sort at every key width).
PAD_SORT_MIN = 1 << 13

#: Largest bound of the keys that NumPy's stable sort orders by radix sort (8- and 16-bit
#: integers); below :data:`RADIX_SORT_MIN` keys it is 2 to 7 times faster than torch's
#: comparison sort (docs/benchmarks.md, "Small sorts").
NUMPY_RADIX_BOUND = 1 << 15


def stable_sort_small(
    keys: Tensor, bound: int | None = None, *, narrow: bool = False
) -> tuple[Tensor, Tensor]:
    """Stable sort of non-negative int64 ``keys < bound``: ``(sorted int64 keys, permutation)``.

    The keys are sorted as uint8 (below 256), int16 or int32 when ``bound`` (by default
    ``max(keys) + 1``) allows: two to five times faster than int64 on the CPU. On a CPU whose
    torch build has the radix sort, 8,192 to 32,767 keys are padded to :data:`RADIX_SORT_MIN`
    with ``bound - 1`` (the sort is stable, so the padding lands after every real key and the
    first ``n`` results are the plain sort's), which is several times faster there; fewer
    than 32,768 CPU keys below :data:`NUMPY_RADIX_BOUND` go through NumPy's stable sort, a
    radix sort for 8- and 16-bit keys.
    With ``narrow=True`` the sorted keys come back as :func:`narrow_dtype` ``(bound)`` (int16,
    int32 or int64: a quarter or half of the memory of int64 keys).

    Example:
        >>> keys = torch.tensor([2, 0, 2, 1])
        >>> values, order = stable_sort_small(keys, 3)
        >>> values.tolist(), order.tolist()
        ([0, 1, 2, 2], [1, 3, 0, 2])
    """
    if bound is None:
        bound = int(keys.max()) + 1 if keys.numel() else 0
    n = keys.shape[0]
    if NUMPY_ON_CPU and keys.device.type == "cpu" and n < RADIX_SORT_MIN and (
            bound <= NUMPY_RADIX_BOUND):
        # The order of a stable sort is unique: NumPy's radix sort gives torch's, faster.
        small = keys.to(torch.uint8 if bound <= 1 << 8 else torch.int16).numpy()
        perm = np.argsort(small, kind="stable").astype(np.int64, copy=False)
        ordered = torch.from_numpy(small[perm])
        return ordered.to(torch.int16 if narrow else torch.int64), torch.from_numpy(perm)
    if RADIX_SORT and keys.device.type == "cpu" and PAD_SORT_MIN <= n < RADIX_SORT_MIN:
        padded = torch.full((RADIX_SORT_MIN,), bound - 1, dtype=keys.dtype)
        padded[:n] = keys
        values, order = _sort_narrow(padded, bound, narrow)
        return values[:n], order[:n]
    return _sort_narrow(keys, bound, narrow)


def narrow_dtype(bound: int) -> torch.dtype:
    """The narrowest of int16, int32 and int64 that holds every integer in ``[0, bound)``.

    Example:
        >>> narrow_dtype(1 << 15), narrow_dtype((1 << 15) + 1), narrow_dtype(1 << 40)
        (torch.int16, torch.int32, torch.int64)
    """
    if bound <= 1 << 15:
        return torch.int16
    if bound <= 1 << 31:
        return torch.int32
    return torch.int64


def _sort_narrow(keys: Tensor, bound: int, narrow: bool) -> tuple[Tensor, Tensor]:
    dtype = narrow_dtype(bound)
    if bound <= 1 << 8:  # sorted as uint8: one radix pass, about twice as fast as int16
        values, order = torch.sort(keys.to(torch.uint8), stable=True)
        return values.to(dtype if narrow else torch.int64), order
    values, order = torch.sort(keys.to(dtype), stable=True)
    return (values if narrow else values.to(torch.int64)), order


# --- Integer division ----------------------------------------------------------------------


def divide(values: Tensor, divisor: int | Tensor, *, out: Tensor | None = None) -> Tensor:
    """``floor(values / divisor)`` for int64 ``values`` of any sign, as a new tensor (or ``out``).

    Args:
        values: int64 tensor.
        divisor: a positive int, or a positive int64 tensor broadcastable to ``values``.
        out: optional output tensor.

    Example:
        >>> divide(torch.tensor([-5, 5, 7]), 2).tolist(), divide(torch.tensor([-5, 7]), 3).tolist()
        ([-3, 2, 3], [-2, 2])
    """
    if isinstance(divisor, int) and divisor & (divisor - 1) == 0:
        # A power of two (1 included): an arithmetic shift floors negative values too.
        return torch.bitwise_right_shift(values, divisor.bit_length() - 1, out=out)
    if _numpy(values) and (isinstance(divisor, int) or divisor.device.type == "cpu"):
        # NumPy's floor division: about 5x torch's on the CPU (262k int64 values).
        quotient = np.floor_divide(values.numpy(), divisor if isinstance(divisor, int) else
                                   divisor.numpy(), out=None if out is None else out.numpy())
        return out if out is not None else torch.from_numpy(quotient)
    return torch.div(values, divisor, rounding_mode="floor", out=out)


def floor_divide_exact(values: Tensor, divisor: int | Tensor) -> tuple[Tensor, Tensor]:
    """``floor(values / divisor)`` and whether the division is exact, for int64 values.

    Args:
        values: int64 tensor (any sign).
        divisor: a positive int, or a positive int64 tensor broadcastable to ``values``.

    Returns:
        ``(quotient, exact)``: int64 floor quotient and a bool tensor.
    """
    quotient = divide(values, divisor)
    if isinstance(divisor, int) and divisor & (divisor - 1) == 0:
        return quotient, (values & (divisor - 1)) == 0
    return quotient, quotient * divisor == values
