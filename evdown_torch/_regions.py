"""The region geometry of a downscaling factor (private): shared by the whole package.

Region of a pixel, place of a pixel in its region, coordinates of a region id, pixels in a
region. The output sensor size itself is :func:`evdown_torch.checks.output_size`.
"""

from __future__ import annotations

from typing import Protocol

import torch
from torch import Tensor

from evdown_torch._tensors import divide
from evdown_torch.checks import output_size

__all__ = ["pixel_columns", "region_of", "region_pixel_count", "region_xy"]


class Pixels(Protocol):
    """Anything with ``x`` and ``y`` columns (:class:`~evdown_torch.events.Events`)."""

    @property
    def x(self) -> Tensor: ...  # noqa: D102

    @property
    def y(self) -> Tensor: ...  # noqa: D102


def region_of(events: Pixels, factor: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Region coordinates ``(x // fx, y // fy)`` of every event, as new int64 tensors."""
    return divide(events.x, factor[0]), divide(events.y, factor[1])


def pixel_columns(
    events: Pixels, factor: tuple[int, int], regions: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """``(N,)`` int64 place of each event's pixel in its region, ``(y % fy) * fx + x % fx``.

    The column of the pixel in its region's row of pixel ids (the photocurrent kernels'
    ``region_pixel_ids``). ``regions``: the events' :func:`region_of`, when the caller has it.

    Example:
        >>> from types import SimpleNamespace
        >>> pixel_columns(SimpleNamespace(x=torch.tensor([0, 3, 2]), y=torch.tensor([1, 0, 3])),
        ...               (2, 2)).tolist()
        [2, 1, 2]
    """
    fx, fy = factor
    rx, ry = region_of(events, factor) if regions is None else regions
    return torch.sub(events.y, ry, alpha=fy).mul_(fx).add_(events.x).sub_(rx, alpha=fx)


def region_xy(region: Tensor, out_width: int) -> tuple[Tensor, Tensor]:
    """Coordinates ``(x, y)`` of int64 ids ``y * out_width + x``: output regions, or pixels.

    ``out_width``: the width of the grid the ids number (the output sensor's for regions,
    the input sensor's for pixel ids ``y * W + x``).

    Example:
        >>> x, y = region_xy(torch.tensor([0, 4, 7]), 3)
        >>> x.tolist(), y.tolist()
        ([0, 1, 1], [0, 1, 2])
    """
    y = divide(region, out_width)
    return region - y * out_width, y


def region_pixel_count(
    region: Tensor, sensor_size: tuple[int, int, int], factor: tuple[int, int]
) -> Tensor:
    """``n_r``: number of sensor pixels in each region (fewer in the last column/row).

    Region ids past ``Ho * Wo`` are those of a batch of recordings stacked vertically
    (recording ``b``'s region ``r`` is ``b * Ho * Wo + r``): each has the ``n_r`` of ``r``.

    Args:
        region: int64 region ids ``ry * Wo + rx``.
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.

    Returns:
        int64 tensor of the shape of ``region``.

    Example:
        >>> region_pixel_count(torch.arange(4), (5, 3, 2), (2, 2)).tolist()  # Wo = 3
        [4, 4, 2, 2]
    """
    w, h, _ = sensor_size
    fx, fy = factor
    out_w, out_h, _ = output_size(sensor_size, factor)
    rx, ry = region_xy(region, out_w)
    ry = torch.remainder(ry, out_h)
    return torch.clamp(w - rx * fx, max=fx) * torch.clamp(h - ry * fy, max=fy)
