"""What a bounded-delay estimation session keeps between chunks (:mod:`.stream`'s steps).

Its own module so that the compiled session step (:mod:`..compiled.linear_stream`), which
makes and reads it too, needs nothing else of the estimation package.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

from evdown_torch.events import Events

__all__ = ["WindowState"]


class WindowState(NamedTuple):
    """What a bounded-delay estimation stream keeps between chunks.

    Attributes:
        t_start: ``()`` first timestamp of the stream (the events' ``t`` dtype).
        t_last: ``()`` last timestamp so far.
        horizon: output events earlier than this time have been returned (a Python number;
            ``None`` before the first chunk).
        knots: the knot events the future needs, one per (pixel, time), in stable time
            order (see :mod:`.stream`).
        change: ``(K,)`` int64 level change of each knot event (a pixel's first carries its
            whole level).
        pixel_t: ``(W * H,)`` time of each pixel's last knot (``t_start`` before its first).
        q: ``(Wo * Ho,)`` int64 reference index of each output region after its last
            breakpoint earlier than ``horizon``.
        returned: ``(Wo * Ho,)`` int64 count of each region's crossings after that
            breakpoint that have been returned (the first of its piece that crosses the
            horizon). The next window drops as many of that piece's crossings, by their
            order, not by their times: a float time computed in another window may fall on
            the other side of the horizon.
    """

    t_start: Tensor
    t_last: Tensor
    horizon: int | float | None
    knots: Events
    change: Tensor
    pixel_t: Tensor
    q: Tensor
    returned: Tensor
