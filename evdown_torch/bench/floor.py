"""The floor of the live replay: read each event and count it in its output region, compiled.

``evdown bench --realtime`` replays this beside the methods, in the same run and the same
chunks, and gives each method's sustained rate over the floor's (column "x floor"): what a
method costs beyond the one pass over the events that no downscaler can avoid. The floor reads
the chunk's ``x`` and ``y`` fields where they lie (no conversion) and adds one to its region's
count with a compiled loop (:mod:`evdown_torch.transforms.functional.compiled.floor`); it
needs Numba.
"""

from __future__ import annotations

import numpy as np

from evdown_torch.checks import check_factor, check_sensor_size, output_size
from evdown_torch.events import DVS_DTYPE
from evdown_torch.transforms.functional.compiled import numba_available

__all__ = ["FloorSession", "RegionFloor"]


class RegionFloor:
    """The floor as a replayable transform: :meth:`session` gives a :class:`FloorSession`.

    Args:
        sensor_size: input ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``.
    """

    def __init__(self, sensor_size: tuple[int, int, int], factor: int | tuple[int, int]):
        self.sensor_size = check_sensor_size(sensor_size)
        self.factor = check_factor(factor, self.sensor_size)

    def algorithmic_delay(self) -> float:
        """0: the floor counts each event as it comes."""
        return 0.0

    def session(self) -> FloorSession:
        """A fresh count of every region.

        Raises:
            NotImplementedError: without Numba (the floor is a compiled loop or nothing).
        """
        if not numba_available():
            raise NotImplementedError("the floor is a compiled loop: it needs numba "
                                      "(pip install 'evdown_torch[compiled]')")
        return FloorSession(self)


class FloorSession:
    """Counts the events of each output region over consecutive chunks; returns no events.

    Attributes:
        counts: ``(Ho * Wo,)`` int64 events counted in each region so far.

    Example:
        >>> chunk = np.zeros(3, dtype=DVS_DTYPE)
        >>> chunk["x"], chunk["y"] = [0, 3, 3], [0, 0, 2]
        >>> session = RegionFloor((4, 4, 2), 2).session()
        >>> len(session(chunk)), session.counts.tolist()
        (0, [1, 1, 0, 1])
    """

    def __init__(self, floor: RegionFloor) -> None:
        out_w, out_h, _ = output_size(floor.sensor_size, floor.factor)
        self.factor, self.out_size = floor.factor, (out_w, out_h)
        self.counts = np.zeros(out_w * out_h, dtype=np.int64)

    def __call__(self, chunk: np.ndarray) -> np.ndarray:
        """Count a chunk (a Tonic structured array) in its regions; returns ``chunk[:0]``."""
        from evdown_torch.transforms.functional.compiled.floor import count_regions

        count_regions(chunk["x"], chunk["y"], self.factor, self.out_size, self.counts)
        return chunk[:0]

    def flush(self) -> np.ndarray:
        """The end of the stream decides nothing: an empty structured array."""
        return np.empty(0, dtype=DVS_DTYPE)
