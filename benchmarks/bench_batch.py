"""Many small recordings in one call (issue 16): batched throughput against a 1M-event stream.

For every method, on one thread: the throughput (input events per second) of

* ``single``: one call per recording, on recordings of N-MNIST size (34 x 34 sensor, about
  4,300 events, 0.3 s each);
* ``batch``: ``transform.batch`` on batches of ``--batch`` such recordings (the list of
  Tonic structured arrays in, the list of outputs back: conversions included);
* ``stream``: one call on one stream of ``--events`` events (default 1M) on the same sensor at
  the same event rate;

the goal ratio ``batch / stream`` (issue 16 asks >= 0.5), and the time of one call on the real
N-MNIST recording (``shared/data/sample_nmnist.bin`` beside the repository, 4,325 events;
issue 16 asks the per-call overhead of such calls at least halved). With ``--device cuda``
(when available) the batch goes through :class:`~evdown_torch.collate.EventBatch` on the GPU.

Timing: the batch and the stream of a method are timed alternately in the same loop (so a
change of machine load hits both), with Python's garbage collector paused, for at least
``--repeats`` rounds and at least ``--min-seconds`` of calls; the figures are medians. The
single calls and the N-MNIST call are medians likewise.

Run: ``python benchmarks/bench_batch.py [--batch 256] [--events 1000000] [--repeats 5]
[--min-seconds 1.0] [--methods ...] [--device cpu] [--short]``. ``--short`` (a few seconds,
for checking that it works) uses batches of 16 and a 50,000-event stream.
"""

from __future__ import annotations

import argparse
import gc
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evdown_torch.bench.inputs import dvs_like_stream, read_nmnist  # noqa: E402
from evdown_torch.bench.lineup import BENCH_SETTINGS  # noqa: E402
from evdown_torch.collate import EventBatch  # noqa: E402
from evdown_torch.transforms.registry import METHODS, make_method  # noqa: E402

SENSOR = (34, 34, 2)
FACTOR = 4
RECORDING_EVENTS = 4_300
RECORDING_US = 300_000
#: The real N-MNIST recording of the project's shared data, next to the repository.
NMNIST_FILE = Path(__file__).resolve().parents[2] / "shared" / "data" / "sample_nmnist.bin"


def timed(call: Callable[[], object]) -> float:
    """Seconds of one call (GPU work included)."""
    start = time.perf_counter()
    call()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return time.perf_counter() - start


def median_times(
    calls: list[Callable[[], object]], repeats: int, min_seconds: float
) -> list[float]:
    """Median seconds of each call, timed alternately after one warm-up call each.

    The calls run for at least ``repeats`` rounds and ``min_seconds`` in all.
    """
    for call in calls:
        call()
    times: list[list[float]] = [[] for _ in calls]
    gc.collect()
    gc.disable()  # no collection pause inside a timed call
    try:
        start = time.perf_counter()
        while len(times[0]) < repeats or time.perf_counter() - start < min_seconds:
            for call, record in zip(calls, times, strict=True):
                record.append(timed(call))
    finally:
        gc.enable()
    return [statistics.median(record) for record in times]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=256, help="recordings per batch")
    parser.add_argument("--events", type=int, default=1_000_000, help="events of the stream")
    parser.add_argument("--repeats", type=int, default=5, help="fewest timed calls of each")
    parser.add_argument("--min-seconds", type=float, default=1.0,
                        help="least time spent timing each method (more repeats if shorter)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--device", default="cpu", help="cpu or cuda (batched path only)")
    parser.add_argument("--short", action="store_true", help="tiny sizes, to check it runs")
    args = parser.parse_args(argv)
    if args.short:
        args.batch, args.events, args.repeats, args.min_seconds = 16, 50_000, 1, 0.0
    torch.set_num_threads(1)
    recordings = [
        dvs_like_stream(RECORDING_EVENTS, SENSOR, duration_us=RECORDING_US, seed=seed)
        for seed in range(args.batch)
    ]
    n_batch = sum(len(r) for r in recordings)
    stream_us = int(RECORDING_US * args.events / RECORDING_EVENTS)
    stream = dvs_like_stream(args.events, SENSOR, duration_us=stream_us, seed=10_000)
    on_device = EventBatch.from_recordings(recordings).to(args.device)
    nmnist = read_nmnist(NMNIST_FILE) if NMNIST_FILE.is_file() else None
    print(f"{args.batch} recordings of {RECORDING_EVENTS} events on {SENSOR}, factor {FACTOR}; "
          f"stream of {args.events:,} events; one thread; device {args.device}; medians")
    if nmnist is None:
        print(f"{NMNIST_FILE} is absent: no N-MNIST column.")
    header = (f"{'method':<12} {'single Mev/s':>13} {'batch Mev/s':>12} {'stream Mev/s':>13} "
              f"{'batch/stream':>13} {'batch/single':>13} {'N-MNIST ms/call':>16}")
    print(header)
    for name in args.methods:
        transform = make_method(name, SENSOR, FACTOR, **BENCH_SETTINGS.get(name, {}))
        (single,) = median_times([lambda t=transform: [t(r) for r in recordings]],
                                 args.repeats, args.min_seconds)
        if args.device == "cpu":
            batch_call = lambda t=transform: t.batch(recordings)  # noqa: E731
        else:
            batch_call = lambda t=transform: t.batch(on_device)  # noqa: E731
        batch, whole = median_times([batch_call, lambda t=transform: t(stream)],
                                    args.repeats, args.min_seconds)
        per_call = "n/a"
        if nmnist is not None:
            (one,) = median_times([lambda t=transform: t(nmnist)], max(args.repeats, 20),
                                  args.min_seconds / 2)
            per_call = f"{one * 1e3:.3f}"
        rates = [n_batch / single / 1e6, n_batch / batch / 1e6, args.events / whole / 1e6]
        print(f"{name:<12} {rates[0]:>13.2f} {rates[1]:>12.2f} {rates[2]:>13.2f} "
              f"{rates[1] / rates[2]:>13.2f} {rates[1] / rates[0]:>13.1f} {per_call:>16}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
