"""What a live chunk costs on a small and on a large sensor: its events, or the sensor's area?

A kernel should cost what a chunk's events cost, not the sensor's area (``STYLE.md``). This
script runs a session of each method over the same number of chunks of the same number of
events (a DVS-like stream of bars, :func:`~evdown_torch.bench.inputs.dvs_like_stream`, 2,500
events a chunk by default: a 1 ms chunk of a 2.5 M events/s sensor) on a 128x128 and on a
1280x720 sensor, one thread, and prints the median chunk time (ms) on each and the ratio
large / small. A ratio near 1 is a chunk that costs its events; a method whose call touches
a per-pixel map or state of the whole sensor shows a ratio near the areas' ratio (56). The
last column says whether each session gave the eager kernels' events (a session with the
eager kernels forced, untimed).

The first chunk of each session warms up (and compiles) and is not timed. Run it on an
otherwise idle machine, ``--runs`` times alternated; EventCount is the control (its session
keeps per-region state only). Each method runs with the live replay's settings
(:data:`~evdown_torch.bench.realtime.REALTIME_SETTINGS`: ``max_delay`` for the estimators).

``--fired``: a long stream's steady state. Before the bars, the session reads one chunk in
which every pixel of the sensor fires once (an ON event each, in a random order over the
millisecond before the bars start, untimed), as after a long recording in which background
activity alone has reached every pixel: a session whose state grows with the pixels that
have fired then shows it in every chunk.

Run: ``python benchmarks/bench_sensor_area.py [--chunk-events 2500] [--chunks 40]
[--runs 3] [--eager] [--fired] [--methods poisson density event_count]`` (``--eager``: time
the eager kernels).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Sequence

import numpy as np
import torch

from evdown_torch import eager_kernels
from evdown_torch.bench.inputs import dvs_like_stream
from evdown_torch.bench.realtime import REALTIME_SETTINGS
from evdown_torch.events import DVS_DTYPE
from evdown_torch.transforms.registry import make_method

SENSORS = ((128, 128, 2), (1280, 720, 2))


#: Microseconds before the bars in which ``--fired``'s chunk fires every pixel.
FIRED_US = 1_000


def every_pixel_fired(sensor: tuple[int, int, int], seed: int = 1) -> np.ndarray:
    """One ON event at each pixel of ``sensor``, in a random order over ``[0, FIRED_US)``.

    Example:
        >>> ev = every_pixel_fired((4, 3, 2))
        >>> len(ev), len(set(zip(ev["x"].tolist(), ev["y"].tolist()))), bool(ev["p"].all())
        (12, 12, True)
    """
    width, height, _ = sensor
    rng = np.random.default_rng(seed)
    pixel = rng.permutation(width * height)
    events = np.zeros(width * height, dtype=DVS_DTYPE)
    events["x"], events["y"] = pixel % width, pixel // width
    events["t"] = np.sort(rng.integers(0, FIRED_US, width * height))
    events["p"] = True
    return events


def session_run(method: str, sensor: tuple[int, int, int], chunk_events: int,
                chunks: int, *, fired: bool = False) -> tuple[list[float], np.ndarray]:
    """A session of ``method`` at factor 4: each chunk's seconds and every output event.

    The first chunk is not timed; the flush's events are among the outputs. ``fired``: the
    session first reads :func:`every_pixel_fired` (untimed, its output among the outputs),
    and the bars start after it.
    """
    events = dvs_like_stream(chunk_events * (chunks + 1), sensor,
                             duration_us=1_000 * (chunks + 1), seed=1,
                             start_us=FIRED_US if fired else 0)
    session = make_method(method, sensor, 4, **REALTIME_SETTINGS.get(method, {})).session()
    seconds, outputs = [], [session(every_pixel_fired(sensor))] if fired else []
    for k in range(chunks + 1):
        chunk = events[k * chunk_events:(k + 1) * chunk_events]
        start = time.perf_counter()
        outputs.append(session(chunk))
        if k:
            seconds.append(time.perf_counter() - start)
    outputs.append(session.flush())
    return seconds, np.concatenate(outputs)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--chunk-events", type=int, default=2_500)
    parser.add_argument("--chunks", type=int, default=40)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--eager", action="store_true", help="time the eager kernels")
    parser.add_argument("--fired", action="store_true",
                        help="every pixel fires once before the bars (a long stream's state)")
    parser.add_argument("--methods", nargs="+", default=["poisson", "density", "event_count"])
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(f"{args.chunk_events:,} events a chunk, {args.chunks} chunks timed, one thread, "
          f"{'eager' if args.eager else 'default'} kernels"
          f"{', after every pixel fired once' if args.fired else ''}")
    print("| method | run | 128x128 median (ms) | 1280x720 median (ms) | large / small "
          "| the eager kernels' events |")
    print("|---|---|---|---|---|---|")
    for run in range(args.runs):
        for method in args.methods:
            medians, same = [], True
            for sensor in SENSORS:
                with eager_kernels(args.eager):
                    seconds, out = session_run(method, sensor, args.chunk_events, args.chunks,
                                               fired=args.fired)
                if run == 0:
                    with eager_kernels():
                        same &= np.array_equal(out, session_run(
                            method, sensor, args.chunk_events, args.chunks,
                            fired=args.fired)[1])
                medians.append(statistics.median(seconds))
            small, large = medians
            print(f"| {method} | {run + 1} | {small * 1e3:.3f} | {large * 1e3:.3f} | "
                  f"{large / small:.2f} | {('yes' if same else 'NO') if run == 0 else ''} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
