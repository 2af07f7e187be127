"""Machinery shared by the kernels: time ordering and region indexing."""

from __future__ import annotations

import torch
from torch import Tensor

from evdown_torch.events import Events


def time_order(t: Tensor) -> Tensor | None:
    """Stable permutation that sorts ``t``, or ``None`` when ``t`` is already sorted.

    Args:
        t: ``(N,)`` timestamps.

    Returns:
        ``(N,)`` int64 indices (ties keep input order), or ``None`` for a sorted input.
    """
    if t.shape[0] < 2 or bool((t[1:] >= t[:-1]).all()):
        return None
    return torch.sort(t, stable=True).indices


#: Events per chunk when a kernel processes a long stream piece by piece: temporaries of this
#: length stay small enough (8 MB of int64) to be recycled by the allocator instead of being
#: mapped afresh, which costs more than the arithmetic on them.
CHUNK_EVENTS = 1 << 20


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


def sort_by_time(events: Events) -> Events:
    """Events in stable time order (the input itself when already sorted)."""
    order = time_order(events.t)
    return events if order is None else events.select(order)


def _divide(values: Tensor, divisor: int) -> Tensor:
    """``values // divisor`` for non-negative int64 values, as a new tensor."""
    if divisor == 1:
        return values.clone()
    if divisor & (divisor - 1) == 0:  # a power of two: a shift is exact and cheaper
        return values >> (divisor.bit_length() - 1)
    return torch.div(values, divisor, rounding_mode="floor")


def floor_divide_exact(values: Tensor, divisor: int | Tensor) -> tuple[Tensor, Tensor]:
    """``floor(values / divisor)`` and whether the division is exact, for int64 values.

    Args:
        values: int64 tensor (any sign).
        divisor: a positive int, or a positive int64 tensor broadcastable to ``values``.

    Returns:
        ``(quotient, exact)``: int64 floor quotient and a bool tensor.
    """
    if isinstance(divisor, int) and divisor & (divisor - 1) == 0:
        shift = divisor.bit_length() - 1  # arithmetic shift floors negative values too
        return values >> shift, (values & (divisor - 1)) == 0
    quotient = torch.div(values, divisor, rounding_mode="floor")
    return quotient, quotient * divisor == values


def region_of(events: Events, factor: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Region coordinates ``(x // fx, y // fy)`` of every event, as new int64 tensors."""
    return _divide(events.x, factor[0]), _divide(events.y, factor[1])
