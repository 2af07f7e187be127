"""The subsamplers' draws compiled: one pass of the two hash chains per event.

:func:`~evdown_torch.transforms.functional.draws.event_uniforms` hashes each event with two
chains of MurmurHash3's 32-bit finaliser over six 32-bit words, about sixty int64 tensor
passes; on the live replay's chunks that was a quarter of PoissonSubsampling's time. This loop
runs the same integer arithmetic event by event (products of two 32-bit values in uint64,
which never overflow, then the low 32 bits: what ``_mul32`` computes in two halves), so the
draws are the same, bit for bit.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import columns_of

__all__ = ["event_uniforms"]

_MASK32 = 0xFFFFFFFF


@compiled_loop
def _fmix32(h: np.uint64) -> np.uint64:  # pragma: no cover - compiled
    """MurmurHash3's 32-bit finaliser on ``h`` in ``[0, 2**32)``."""
    mask = np.uint64(_MASK32)
    h ^= h >> np.uint64(16)
    h = (h * np.uint64(0x85EBCA6B)) & mask
    h ^= h >> np.uint64(13)
    h = (h * np.uint64(0xC2B2AE35)) & mask
    return h ^ (h >> np.uint64(16))


@compiled_loop
def _uniforms_loop(
    index: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, offset: np.ndarray,
    start_high: int, start_low: int, out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out[i]``: the 53 bits of event ``i``'s two chains as a float64 in ``[0, 1)``."""
    mask = np.int64(_MASK32)
    scale = 2.0 ** -53
    for i in range(index.shape[0]):
        words = (index[i] & mask, (index[i] >> 32) & mask, x[i] & mask,
                 ((y[i] << 1) | (1 if p[i] else 0)) & mask, offset[i] & mask,
                 (offset[i] >> 32) & mask)
        high = np.uint64(start_high)
        low = np.uint64(start_low)
        for word in words:
            high = _fmix32(high ^ np.uint64(word))
            low = _fmix32(low ^ np.uint64(word))
        out[i] = np.float64((high << np.uint64(21)) | (low >> np.uint64(11))) * scale


def event_uniforms(events: Events, key: int, index: Tensor, offset: Tensor) -> Tensor:
    """The draws of :func:`~evdown_torch.transforms.functional.draws.event_uniforms`, compiled.

    Args:
        events: ``N`` events on the CPU.
        key: the mixed seed (63 bits).
        index: ``(N,)`` int64 position of each event in its stream.
        offset: ``(N,)`` int64 ``t - origin`` (a float's bits, for float ``t``).

    Returns:
        ``(N,)`` float64 in ``[0, 1)``: the same draws (a new tensor).
    """
    out = np.empty(index.shape[0], dtype=np.float64)
    _uniforms_loop(*columns_of(index, events.x, events.y, events.p, offset),
                   key & _MASK32, (key >> 32) & _MASK32, out)
    return torch.from_numpy(out)
