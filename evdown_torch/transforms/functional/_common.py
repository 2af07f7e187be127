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


def take(values: Tensor, index: Tensor) -> Tensor:
    """``values[index]`` for a 1-D int64 ``index`` (``index_select``: much faster on the CPU)."""
    return values.index_select(0, index)


def where_true(mask: Tensor) -> Tensor:
    """``(M,)`` int64 positions of the True entries of a 1-D bool ``mask``, ascending."""
    return torch.nonzero(mask).squeeze(1)


def sort_by_time(events: Events) -> Events:
    """Events in stable time order (the input itself when already sorted)."""
    order = time_order(events.t)
    return events if order is None else events.select(order)


def divide(values: Tensor, divisor: int, *, out: Tensor | None = None) -> Tensor:
    """``values // divisor`` for non-negative int64 values, as a new tensor (or into ``out``)."""
    if divisor & (divisor - 1) == 0:  # a power of two (1 included): a shift is exact, cheaper
        return torch.bitwise_right_shift(values, divisor.bit_length() - 1, out=out)
    return torch.div(values, divisor, rounding_mode="floor", out=out)


def stable_sort_small(keys: Tensor, bound: int | None = None) -> tuple[Tensor, Tensor]:
    """Stable sort of non-negative int64 ``keys < bound``: ``(sorted int64 keys, permutation)``.

    The keys are sorted as int16 or int32 when ``bound`` (by default ``max(keys) + 1``)
    allows: two to three times faster than int64 on the CPU.
    """
    if bound is None:
        bound = int(keys.max()) + 1 if keys.numel() else 0
    if bound <= 1 << 15:
        small = keys.to(torch.int16)
    elif bound <= 1 << 31:
        small = keys.to(torch.int32)
    else:
        small = keys
    values, order = torch.sort(small, stable=True)
    return values.to(torch.int64), order


def region_xy(region: Tensor, out_width: int) -> tuple[Tensor, Tensor]:
    """Output coordinates ``(x, y)`` of int64 region ids ``y * out_width + x``."""
    y = torch.div(region, out_width, rounding_mode="floor")
    return region - y * out_width, y


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
    return divide(events.x, factor[0]), divide(events.y, factor[1])
