"""Many small recordings in one call (issue 16): batched throughput against a 1M-event stream.

For every method, on one thread: the throughput (input events per second) of

* ``single``: one call per recording, on recordings of N-MNIST size (34 x 34 sensor, about
  4,300 events, 0.3 s each);
* ``batch``: ``transform.batch`` on batches of ``--batch`` such recordings (the list of
  Tonic structured arrays in, the list of outputs back: conversions included);
* ``stream``: one call on one stream of ``--events`` events (default 1M) on the same sensor at
  the same event rate;

and the goal ratio ``batch / stream`` (issue 16 asks >= 0.5). With ``--device cuda`` (when
available) the batch goes through :class:`~evdown_torch.collate.EventBatch` on the GPU.

Run: ``python benchmarks/bench_batch.py [--batch 256] [--events 1000000] [--repeats 5]
[--methods ...] [--device cpu] [--short]``. ``--short`` (a few seconds, for checking that it
works) uses batches of 16 and a 50,000-event stream.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evdown_torch.bench.inputs import dvs_like_stream  # noqa: E402
from evdown_torch.bench.lineup import BENCH_SETTINGS  # noqa: E402
from evdown_torch.collate import EventBatch  # noqa: E402
from evdown_torch.transforms.registry import METHODS, make_method  # noqa: E402

SENSOR = (34, 34, 2)
FACTOR = 4
RECORDING_EVENTS = 4_300
RECORDING_US = 300_000


def best_time(call: Callable[[], object], repeats: int) -> float:
    """Fastest of ``repeats`` timed calls (after one warm-up call), in seconds."""
    call()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return min(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=256, help="recordings per batch")
    parser.add_argument("--events", type=int, default=1_000_000, help="events of the stream")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--device", default="cpu", help="cpu or cuda (batched path only)")
    parser.add_argument("--short", action="store_true", help="tiny sizes, to check it runs")
    args = parser.parse_args(argv)
    if args.short:
        args.batch, args.events, args.repeats = 16, 50_000, 1
    torch.set_num_threads(1)
    recordings = [
        dvs_like_stream(RECORDING_EVENTS, SENSOR, duration_us=RECORDING_US, seed=seed)
        for seed in range(args.batch)
    ]
    n_batch = sum(len(r) for r in recordings)
    stream_us = int(RECORDING_US * args.events / RECORDING_EVENTS)
    stream = dvs_like_stream(args.events, SENSOR, duration_us=stream_us, seed=10_000)
    on_device = EventBatch.from_recordings(recordings).to(args.device)
    print(f"{args.batch} recordings of {RECORDING_EVENTS} events on {SENSOR}, factor {FACTOR}; "
          f"stream of {args.events:,} events; one thread; device {args.device}")
    header = (f"{'method':<12} {'single Mev/s':>13} {'batch Mev/s':>12} {'stream Mev/s':>13} "
              f"{'batch/stream':>13} {'batch/single':>13}")
    print(header)
    for name in args.methods:
        transform = make_method(name, SENSOR, FACTOR, **BENCH_SETTINGS.get(name, {}))
        single = best_time(lambda t=transform: [t(r) for r in recordings], args.repeats)
        if args.device == "cpu":
            batch = best_time(lambda t=transform: t.batch(recordings), args.repeats)
        else:
            batch = best_time(lambda t=transform: t.batch(on_device), args.repeats)
        whole = best_time(lambda t=transform: t(stream), args.repeats)
        rates = [n_batch / single / 1e6, n_batch / batch / 1e6, args.events / whole / 1e6]
        print(f"{name:<12} {rates[0]:>13.2f} {rates[1]:>12.2f} {rates[2]:>13.2f} "
              f"{rates[1] / rates[2]:>13.2f} {rates[1] / rates[0]:>13.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
