"""How fast :func:`evdown_torch.io.read_events` reads each format, and expelliarmus beside it.

Run: ``python benchmarks/bench_readers.py [--events N] [--repeats R]`` (default 2,000,000
events, best of 3 reads, one thread). It writes uniformly random events on a 1280 x 720 sensor
over 10 s to a temporary folder as ``.npy``, ``.h5``, Prophesee EVT 2.0 and EVT 3.0 ``.raw``
and DAT (encoded word by word from the formats' documentation), reads each back with
``read_events``, checks the events, and prints millions of events per second. Where
expelliarmus is installed it reads the EVT 2.0 and DAT files too, for comparison (not EVT 3.0:
it misreads its time, see :mod:`evdown_torch.io`).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from evdown_torch.events import DVS_DTYPE
from evdown_torch.io import read_events, write_events


def random_events(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    events = np.empty(n, DVS_DTYPE)
    events["x"], events["y"] = rng.integers(0, 1280, n), rng.integers(0, 720, n)
    events["t"], events["p"] = np.sort(rng.integers(0, 10_000_000, n)), rng.random(n) < 0.5
    return events


def _ints(events: np.ndarray) -> tuple[np.ndarray, ...]:
    return tuple(events[f].astype(np.int64) for f in ("t", "x", "y", "p"))


def evt2(events: np.ndarray) -> bytes:
    t, x, y, p = _ints(events)
    words = np.stack([0x8 << 28 | t >> 6, p << 28 | (t & 63) << 22 | x << 11 | y], axis=1)
    return b"% evt 2.0\n% geometry 1280x720\n% end\n" + words.astype("<u4").tobytes()


def evt3(events: np.ndarray) -> bytes:
    t, x, y, p = _ints(events)  # a TIME_HIGH word before every event: valid, if verbose
    words = np.stack([0x8000 | (t >> 12) & 0xFFF, 0x6000 | t & 0xFFF, y, 0x2000 | p << 11 | x],
                     axis=1)
    return b"% evt 3.0\n% geometry 1280x720\n% end\n" + words.astype("<u2").tobytes()


def dat(events: np.ndarray) -> bytes:
    t, x, y, p = _ints(events)
    words = np.stack([t, x | y << 14 | p << 28], axis=1)
    head = b"% Data file containing CD events\n% Version 2\n% Width 1280\n% Height 720\n"
    return head + bytes([0x0C, 8]) + words.astype("<u4").tobytes()


def best_seconds(read, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        read()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=2_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    events = random_events(args.events)
    folder = Path(tempfile.mkdtemp())
    write_events(folder / "rec.npy", events)
    write_events(folder / "rec.h5", events, sensor_size=(1280, 720, 2))
    (folder / "evt2.raw").write_bytes(evt2(events))
    (folder / "evt3.raw").write_bytes(evt3(events))
    (folder / "rec.dat").write_bytes(dat(events))
    print(f"{args.events} events, best of {args.repeats} reads")
    for name in ("rec.npy", "rec.h5", "evt2.raw", "evt3.raw", "rec.dat"):
        path = folder / name
        got = read_events(path, sensor_size=(1280, 720, 2)).events
        assert np.array_equal(got["t"], events["t"]) and np.array_equal(got["x"], events["x"])
        seconds = best_seconds(lambda p=path: read_events(p, sensor_size=(1280, 720, 2)),
                               args.repeats)
        print(f"read_events {name:9s} {args.events / seconds / 1e6:7.1f} M events/s")
    try:
        from expelliarmus import Wizard
    except ImportError:
        return
    for name, encoding in (("evt2.raw", "evt2"), ("rec.dat", "dat")):
        path = folder / name
        assert np.array_equal(Wizard(encoding=encoding).read(path)["t"], events["t"])
        seconds = best_seconds(lambda p=path, e=encoding: Wizard(encoding=e).read(p),
                               args.repeats)
        print(f"expelliarmus {name:9s}{args.events / seconds / 1e6:7.1f} M events/s")


if __name__ == "__main__":
    main()
