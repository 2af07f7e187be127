"""DensitySubsampling's neighbour lookups compiled: one sweep in stream order per offset group.

:func:`~evdown_torch.transforms.functional.density._density_sorted` needs, for each event and
each offset of its patch, the neighbour pixel's last event up to this one in stream order; the
eager kernel finds it by a binary search over the events grouped by pixel (half of its time
on the live replay's chunks). This loop walks the events in stream order keeping each pixel's
latest event (its place among the grouped events) in a table, and reads the neighbours'
there: the same event wherever one exists (where none does, the eager search's answer is not
the neighbour's either, and both paths discard it), so the densities are the same, bit for
bit.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import columns_of

__all__ = ["last_neighbours"]


@compiled_loop
def _last_loop(
    key: np.ndarray, place: np.ndarray, shifts: np.ndarray, planes: int, latest: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Each grouped event's neighbours' last events, sweeping the events in stream order.

    ``out[d, g]``: 1 + the grouped place of the last event at ``key[g] + shifts[d]`` up to
    grouped event ``g`` in stream order (0: none); ``place[e]``: stream event ``e``'s.
    """
    latest[:] = 0
    for e in range(place.shape[0]):
        g = place[e]
        pixel = key[g]
        latest[np.uint64(pixel)] = g + 1
        for d in range(shifts.shape[0]):
            neighbour = pixel + shifts[d]
            if 0 <= neighbour < planes:
                out[d, g] = latest[np.uint64(neighbour)]
            else:
                out[d, g] = 0


def last_neighbours(key: Tensor, place: Tensor, shifts: Tensor, planes: int) -> Tensor:
    """The neighbours' last events, as the eager search finds them where they exist.

    Args:
        key: ``(N,)`` int64 padded pixel key of each event, grouped (by pixel, then stream
            position), each in ``0 .. planes - 1``.
        place: ``(N,)`` int64 grouped place of each event in stream order.
        shifts: ``(D,)`` int64 key offsets of the neighbours.
        planes: the keys' range.

    Returns:
        ``(D, N)`` int64: for offset ``d`` and grouped event ``g``, 1 + the grouped place of
        the neighbour's last event up to ``g`` in stream order, 0 where it has none (the
        places in the eager kernel's arrays, which hold a sentinel in front).
    """
    keys, places, offsets = columns_of(key, place, shifts)
    out = np.empty((offsets.shape[0], keys.shape[0]), dtype=np.int64)
    _last_loop(keys, places, offsets, planes, np.empty(planes, dtype=np.int64), out)
    return torch.from_numpy(out)
