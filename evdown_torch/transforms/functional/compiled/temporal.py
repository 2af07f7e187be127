"""Bins of time compiled (TemporalFunnelling's, PoissonSubsampling's): one division a bin.

The eager :func:`~..temporal.bin_start` takes the offsets, their floor division by ``dt``,
a product and a sum: five passes over the events (about 1.1 ms of a 240,000-event chunk of
the live replay, a quarter of the chain's). Here one pass keeps the bin of the last event and
divides only when an event leaves it: in time order (a session's chunks, every call of
:func:`~..temporal.temporal_funnelling`), once a bin. The same integers as the eager kernel.
:func:`~..temporal.bin_index` takes the same pass for the bins' numbers (PoissonSubsampling's
windows, about 0.6 ms of its live chunk).
"""

from __future__ import annotations

import numpy as np

from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.scratch import scratch_column

__all__ = ["bins"]


@compiled_loop
def _bins_loop(
    t: np.ndarray, origin: int, step: int, starts: bool, out: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """``out``: each bin ``floor((t - origin) / step)``, or its start (``starts``); -1 or a wrap.

    The start is ``origin`` plus the bin times ``step``. Returns the first ``i`` whose
    offset ``t[i] - origin`` wraps past ``2**63 - 1`` (negative: ``t >= origin`` holds),
    else -1. ``index`` and ``low`` are the last event's bin and the offset of its start (0
    before the first event: bin 0's).
    """
    index = np.int64(0)
    low = np.int64(0)
    for i in range(t.shape[0]):
        offset = t[i] - origin
        if offset < 0:
            return i
        if offset < low or offset - low >= step:  # (both >= 0: no wrap)
            index = offset // step
            low = index * step
        out[i] = low + origin if starts else index
    return -1


def bins(t: np.ndarray, origin: int, step: int, *, starts: bool) -> np.ndarray | None:
    """Each int64 ``t``'s bin (``floor((t - origin) / step)``) or, with ``starts``, its start.

    Args:
        t: ``(N,)`` int64 timestamps ``>= origin``, in any order (time order costs one
            division a bin).
        origin: the first bin's start.
        step: the bin length, ``1 <= step <= 2**63 - 1``.
        starts: the bins' starts (``origin + bin * step``), else their numbers.

    Returns:
        An ``(N,)`` int64 column, this thread's scratch column
        (:func:`~.scratch.scratch_column`: memory no other object refers to, often the last
        call's), or ``None`` where an offset ``t - origin`` does not fit in int64 (the caller
        raises its error).

    Example:
        >>> bins(np.array([3, 9, 10, 25, 4]), 3, 10, starts=True).tolist()
        [3, 3, 3, 23, 3]
        >>> bins(np.array([3, 9, 10, 25, 4]), 3, 10, starts=False).tolist()
        [0, 0, 0, 2, 0]
    """
    out = scratch_column("temporal bins", t.shape[0], np.int64)
    return out if _bins_loop(t, origin, step, starts, out) < 0 else None
