"""Stable sorts, compiled: the order NumPy's stable ``argsort`` gives the keys.

Several loops need a stable order: a LinearEstimation session's state, whose fired pixels'
knots come in no time order (:mod:`.linear_ramps_state`), a window whose regions are sparse
next to its events (:func:`.knots.group_by_region`), a region whose pixels are many next to
its events (:func:`.knots.region_knots`), and the held knots of a bounded-delay window
(:mod:`.estimation_window`). NumPy's stable ``argsort`` gives the same order, but Numba's merge
sort behind it takes about 2.5 s to compile on a first call with a cold cache
(docs/benchmarks.md, "Sixth session of 2026-12-03"), and a comparison sort costs about 45 ns a
key on the state's knots. These plain loops compile in a fraction of a second:
:func:`stable_order`, a radix sort, for many int64 keys over a wide range; :func:`merge_order`,
a merge sort, for a few keys (no table to clear).
"""

from __future__ import annotations

import numpy as np

from evdown_torch.transforms.functional.compiled._numba import compiled_loop

__all__ = ["DIGIT_BITS", "merge_order", "stable_order"]

#: The bits of one digit of :func:`stable_order`'s radix sort.
DIGIT_BITS = 11


@compiled_loop
def stable_order(keys: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """The stable sort's order of int64 ``keys``: a radix sort of ``keys - min(keys)``.

    One count and one scatter per :data:`DIGIT_BITS` bits of the keys' range, low digits
    first (a few passes). Plain loops over int64 (no array methods, no unsigned keys).

    Raises:
        ValueError: for keys spanning ``2**63`` or more (their range wraps int64).
    """
    n = keys.shape[0]
    order = np.empty(n, np.int64)
    key = np.empty(n, np.int64)
    low = keys[0] if n else 0
    high = low
    for i in range(n):
        low = min(low, keys[i])
        high = max(high, keys[i])
    span = high - low
    if span < 0:
        raise ValueError("keys spanning 2**63 or more")
    for i in range(n):
        order[i] = i
        key[i] = keys[i] - low
    spare_order, spare_key = np.empty(n, np.int64), np.empty(n, np.int64)
    count = np.empty((1 << DIGIT_BITS) + 1, np.int64)
    mask = (1 << DIGIT_BITS) - 1
    shift = 0
    while shift < 63 and (span >> shift) > 0:
        for d in range(count.shape[0]):
            count[d] = 0
        for i in range(n):
            count[((key[i] >> shift) & mask) + 1] += 1
        for d in range(1, count.shape[0]):
            count[d] += count[d - 1]
        for i in range(n):
            d = (key[i] >> shift) & mask
            at = count[d]
            spare_order[at], spare_key[at] = order[i], key[i]
            count[d] = at + 1
        for i in range(n):
            order[i], key[i] = spare_order[i], spare_key[i]
        shift += DIGIT_BITS
    return order


@compiled_loop
def merge_order(keys: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """The stable sort's order of ``keys``: a bottom-up merge sort of their indices.

    Runs of 1, 2, 4, ... keys merged pairwise, the left run's key first on a tie (so equal
    keys keep their order): about ``log2(N)`` passes, no table, for a few keys. ``keys``:
    integers, or floats without NaN (timestamps).
    """
    n = keys.shape[0]
    order, spare = np.empty(n, np.int64), np.empty(n, np.int64)
    for i in range(n):
        order[i] = i
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid, hi = min(lo + width, n), min(lo + 2 * width, n)
            i, j = lo, mid
            for k in range(lo, hi):
                if j >= hi or (i < mid and keys[order[i]] <= keys[order[j]]):
                    spare[k] = order[i]
                    i += 1
                else:
                    spare[k] = order[j]
                    j += 1
        order, spare = spare, order
        width *= 2
    return order
