"""The live replay of the design estimates in ``benchmarks/`` (``*_estimate.py``).

Those scripts time a compiled loop that is not part of the package beside the package's own
sessions, on the chunks that ``evdown bench --realtime`` replays: the synthetic gesture
recording retimed to :data:`~.realtime.REALTIME_RATE`, cut into 10 ms chunks. This module
is their one shared front: the command line, the Numba check and the chunks.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np
import torch

from evdown_torch.bench.inputs import gesture_stream
from evdown_torch.bench.realtime import REALTIME_RATE, chunk_bounds_us, retime

__all__ = ["ESTIMATE_CHUNK_US", "estimate_replay"]

#: The chunks' duration in stream time (microseconds).
ESTIMATE_CHUNK_US = 10_000


def estimate_replay(
    argv: Sequence[str] | None, description: str | None, *, compiled: bool,
    sensor_size: tuple[int, int, int] = (128, 128, 2),
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Parse ``--events`` and ``--chunks``, and build the replay an estimate times.

    Sets torch to one thread (the replay's).

    Args:
        argv: the command line's arguments (``None``: ``sys.argv[1:]``).
        description: the script's help text.
        compiled: whether the script's loops can be compiled (its ``import numba`` worked).
        sensor_size: the gesture recording's ``(W, H, P)``.

    Returns:
        ``(stream, bounds, last)``: the retimed recording (a Tonic structured array), the
        start index of each 10 ms chunk and the recording's length after the last, and the
        number of timed chunks (chunk 0 warms up; ``bounds[last + 1]`` ends the last timed
        one). ``None``, with a message on stderr, where the loops cannot be compiled.

    Raises:
        SystemExit: for a recording too short for three chunks (argparse's error).
    """
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--events", type=int, default=13_000_000)
    parser.add_argument("--chunks", type=int, default=50, help="timed 10 ms chunks")
    args = parser.parse_args(argv)
    if not compiled:
        print("this estimate needs numba (pip install 'evdown_torch[compiled]')",
              file=sys.stderr)
        return None
    torch.set_num_threads(1)
    stream, _ = retime(gesture_stream(args.events, sensor_size=sensor_size), REALTIME_RATE)
    bounds = chunk_bounds_us(stream["t"], ESTIMATE_CHUNK_US)
    last = min(args.chunks, len(bounds) - 3)
    if last < 1:
        parser.error("the replay needs at least three 10 ms chunks: give more --events")
    return stream, bounds, last
