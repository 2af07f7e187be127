"""A method's live session with and without the scratch columns, fresh and after a set-up.

On the compiled CPU path the edge's columns (a chunk's fields read from its Tonic array), the
outputs of EventCount, PhotocurrentPooling, Downsample and EventFunnelling, and the columns
of the estimators' window and next-knots loops (``--methods cubic``) come from each thread's
reused scratch columns
(:mod:`evdown_torch.transforms.functional.compiled.scratch`) instead of fresh memory each
call. This script runs sessions of each method over the live replay's chunks (the synthetic
gesture recording retimed to 25 M events/s, 10 ms chunks, one thread, the replay's
settings), ``--laps`` times over (each lap later in time), one with the scratch columns and
one with them switched off (every column new, as before them), ``--runs`` times:

* each in a **fresh** process that only loads the chunks (as a lean live process would run);
* and both in this process, **after the replay's set-up** (building the 13M-event recording
  frees large blocks, after which glibc keeps freed memory in the heap: the set-up
  ``evdown bench --realtime`` runs in).

It prints per method the median chunk time of each run, the median minor page faults of a
chunk (fresh pages touched), the ratio of the total times, and whether every output event
(all held to the end, in order) was the same in every session. The first chunk of each
session warms up and is not timed.

Run: ``python benchmarks/scratch_columns.py [--events 13000000] [--chunks 50] [--laps 3]
[--runs 3] [--methods event_count downsample funnelling photocurrent cubic]`` (the default:
the first four).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script

from evdown_torch.bench.estimates import estimate_replay  # noqa: E402
from evdown_torch.bench.realtime import REALTIME_SETTINGS, minor_faults  # noqa: E402
from evdown_torch.transforms.functional.compiled import (  # noqa: E402
    numba_available,
    scratch,
)
from evdown_torch.transforms.registry import make_method  # noqa: E402

SENSOR = (128, 128, 2)
FACTOR = 4


def run_session(method: str, chunks: list[np.ndarray], laps: int, reuse: bool,
                ) -> dict[str, float | str]:
    """One session over ``laps`` laps of ``chunks``, every chunk but the first timed.

    Returns its median and total seconds, the median minor faults of a chunk and a digest
    of every output event, in order (all held until the end).
    """
    session = make_method(method, SENSOR, FACTOR, **REALTIME_SETTINGS.get(method, {})).session()
    span = int(chunks[-1]["t"][-1]) - int(chunks[0]["t"][0]) + 1
    seconds: list[float] = []
    faults: list[int] = []
    outputs: list[np.ndarray] = []
    largest = scratch.LARGEST_KEPT if reuse else -1  # -1: no column is kept
    with mock.patch.object(scratch, "LARGEST_KEPT", largest):
        for lap in range(laps):
            for k, chunk in enumerate(chunks):
                shifted = chunk.copy()
                shifted["t"] += lap * span
                before, start = minor_faults(), time.perf_counter()
                outputs.append(session(shifted))
                if lap or k:
                    seconds.append(time.perf_counter() - start)
                    faults.append(minor_faults() - before)
    return {"median": statistics.median(seconds), "total": sum(seconds),
            "faults": statistics.median(faults),
            "digest": hashlib.sha256(np.concatenate(outputs).tobytes()).hexdigest()}


def _child(path: str, method: str, laps: int, reuse: bool) -> None:
    """Time one session in this fresh process; print :func:`run_session`'s JSON."""
    with np.load(path) as saved:
        stream, bounds = saved["stream"], saved["bounds"]
    chunks = [stream[int(bounds[k]):int(bounds[k + 1])] for k in range(len(bounds) - 1)]
    del stream
    print(json.dumps(run_session(method, chunks, laps, reuse)))


def _fresh(path: str, method: str, laps: int, reuse: bool) -> dict[str, float | str]:
    command = [sys.executable, __file__, "--child", path, method, str(laps), str(int(reuse))]
    done = subprocess.run(command, capture_output=True, text=True, check=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    return json.loads(done.stdout.strip().splitlines()[-1])


def _row(method: str, label: str,
         pairs: list[tuple[dict[str, float | str], dict[str, float | str]]]) -> str:
    kept = ", ".join(f"{1e3 * k['median']:.2f}" for k, _ in pairs)
    new = ", ".join(f"{1e3 * n['median']:.2f}" for _, n in pairs)
    faults = (f"{statistics.median(k['faults'] for k, _ in pairs):.0f} / "
              f"{statistics.median(n['faults'] for _, n in pairs):.0f}")
    ratios = ", ".join(f"{n['total'] / k['total']:.2f}" for k, n in pairs)
    digests = {str(side["digest"]) for pair in pairs for side in pair}
    same = "yes" if len(digests) == 1 else "NO"
    return f"| {method} | {label} | {kept} | {new} | {faults} | {ratios} | {same} |"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        _, path, method, laps, reuse = argv
        _child(path, method, int(laps), reuse == "1")
        return 0
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--laps", type=int, default=3)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--methods", nargs="+",
                        default=["event_count", "downsample", "funnelling", "photocurrent"])
    own, rest = parser.parse_known_args(argv)
    replay = estimate_replay(rest, __doc__, compiled=numba_available(), sensor_size=SENSOR)
    if replay is None:
        return 2
    stream, bounds, last = replay
    chunks = [stream[int(bounds[k]):int(bounds[k + 1])] for k in range(last + 1)]
    n_events = int(bounds[last + 1] - bounds[0])
    print(f"{len(chunks)} chunks of 10 ms ({n_events:,} events, 25 M/s), {own.laps} laps, "
          f"{own.runs} runs; one thread\n")
    print("| method | process | median chunk (ms), scratch, runs | new columns, runs "
          "| median faults a chunk, scratch / new | new / scratch (total times), runs "
          "| the same events |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        path = str(Path(folder) / "chunks.npz")
        np.savez(path, stream=stream[: int(bounds[last + 1])], bounds=bounds[: last + 2])
        for method in own.methods:
            fresh = [(_fresh(path, method, own.laps, True), _fresh(path, method, own.laps, False))
                     for _ in range(own.runs)]
            warm = [(run_session(method, chunks, own.laps, True),
                     run_session(method, chunks, own.laps, False)) for _ in range(own.runs)]
            for label, pairs in (("fresh", fresh), ("after the replay's set-up", warm)):
                print(_row(method, label, pairs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
