"""The live replay's floor: a compiled loop that reads each event and counts it in its region.

What no downscaler can avoid (reading every event's pixel and finding its output region), as
a yardstick for the methods timed in the same run (``evdown bench --realtime``, column
"x floor"): no method is expected to reach it, and the ratio to it moves far less with the
machine and its load than the rates themselves.
"""

from __future__ import annotations

import numpy as np

from evdown_torch.transforms.functional.compiled._numba import compiled_loop
from evdown_torch.transforms.functional.compiled.regions import outside_error, region_tables

__all__ = ["count_regions"]


@compiled_loop
def _count_loop(
    x: np.ndarray, y: np.ndarray, column: np.ndarray, row: np.ndarray, out_w: int,
    counts: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Add one to ``counts[row[y] * out_w + column[x]]`` for each event.

    Returns ``N``, or ``-1 - i`` for a pixel ``i`` outside the tables.
    """
    width = column.shape[0]
    height = row.shape[0]
    for i in range(x.shape[0]):
        xi = x[i]
        yi = y[i]
        if xi < 0 or xi >= width or yi < 0 or yi >= height:
            return -1 - i
        counts[row[yi] * out_w + column[xi]] += 1
    return x.shape[0]


def count_regions(
    x: np.ndarray, y: np.ndarray, factor: tuple[int, int], out_size: tuple[int, int],
    counts: np.ndarray,
) -> None:
    """Add each event's 1 to its region's count, reading the columns where they lie.

    Args:
        x: ``(N,)`` integer column of each event (any integer dtype; a field of a structured
            array is read in place).
        y: ``(N,)`` integer row.
        factor: ``(fx, fy)``.
        out_size: the output grid ``(Wo, Ho)``.
        counts: ``(Ho * Wo,)`` int64 counts, added to.

    Raises:
        ValueError: for an event outside the sensor of the grid.

    Example:
        >>> counts = np.zeros(4, dtype=np.int64)
        >>> count_regions(np.array([0, 3, 3]), np.array([0, 0, 2]), (2, 2), (2, 2), counts)
        >>> counts.tolist()
        [1, 1, 0, 1]
    """
    column, row = region_tables(factor, out_size[0], out_size[1])
    done = _count_loop(x, y, column, row, out_size[0], counts)
    if done < 0:
        raise outside_error(-1 - done, x, y, column, row)
