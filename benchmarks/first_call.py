"""What the first compiled call of a process costs, with a cold and with a warm Numba cache.

Each run starts two fresh processes sharing a new, empty ``NUMBA_CACHE_DIR``: the first finds
the cache cold (it compiles every loop and fills the cache), the second warm. Each process
imports ``evdown_torch`` (which imports no Numba), then times ``import numba`` and the first
call of each method with a compiled loop, in order, on 100 events (16x16, factor 4), and the
replay's floor; before them, a Tonic structured array read and written back (its column loops,
which every method's first call would otherwise pay). Prints one Markdown table of the ranges
over the runs (``docs/benchmarks.md``, "Compiled CPU kernels").

Run: ``python benchmarks/first_call.py [--runs 3]`` (needs numba).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

ROOT = Path(__file__).resolve().parents[1]

STEPS = ["import numba", "Tonic array in and out", "EventCount", "Downsample", "EventFunnelling",
         "TemporalFunnelling", "PhotocurrentPooling", "LIFPooling", "LinearEstimation",
         "CubicEstimation", "LinearEstimation session (max_delay)", "floor"]


def one_process() -> dict[str, float]:
    """The first calls of this process, in seconds (run in a fresh process)."""
    import numpy as np

    from evdown_torch import (
        CubicEstimation,
        Downsample,
        EventCount,
        EventFunnelling,
        LIFPooling,
        LinearEstimation,
        PhotocurrentPooling,
        TemporalFunnelling,
    )
    from evdown_torch.bench.floor import RegionFloor
    from evdown_torch.events import DVS_DTYPE, from_events, to_events
    from evdown_torch.transforms.functional.compiled import numba_available

    seconds = {}
    start = time.perf_counter()
    if not numba_available():
        raise SystemExit("this script needs numba (pip install 'evdown_torch[compiled]')")
    seconds["import numba"] = time.perf_counter() - start
    ev = np.zeros(100, dtype=DVS_DTYPE)
    i = np.arange(100)
    ev["x"], ev["y"], ev["t"], ev["p"] = i % 16, i % 9, i // 3, i % 3 > 0
    calls: dict[str, Callable[[np.ndarray], object]] = {
        "Tonic array in and out": lambda ev: from_events(*to_events(ev, (16, 16, 2))),
        "EventCount": EventCount((16, 16, 2), 4, threshold=0.5),
        "Downsample": Downsample((16, 16, 2), 4),
        "EventFunnelling": EventFunnelling((16, 16, 2), 4),
        "TemporalFunnelling": TemporalFunnelling(dt=5),
        "PhotocurrentPooling": PhotocurrentPooling((16, 16, 2), 4),
        # steps of 2 us: regions with several cells, so the compiled rounds run
        "LIFPooling": LIFPooling((16, 16, 2), 4, dt=2, tau=10.0),
        # the estimators share one window loop: the first call compiles it for both curves
        "LinearEstimation": LinearEstimation((16, 16, 2), 4, threshold=0.25),
        "CubicEstimation": CubicEstimation((16, 16, 2), 4, threshold=0.25),
        # a bounded-delay session: its steps compile the ramps and the state they make
        "LinearEstimation session (max_delay)": lambda ev: _two_chunks(
            LinearEstimation((16, 16, 2), 4, threshold=0.25, max_delay=10).session(), ev),
        "floor": RegionFloor((16, 16, 2), 4).session(),
    }
    for name, call in calls.items():
        start = time.perf_counter()
        call(ev)
        seconds[name] = time.perf_counter() - start
    return seconds


def _two_chunks(session: Callable[[np.ndarray], object], ev: np.ndarray) -> None:
    session(ev[:50])
    session(ev[50:])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--one-process", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one_process:
        print(json.dumps(one_process()))
        return 0
    found: dict[str, list[dict[str, float]]] = {"cold": [], "warm": []}
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory() as cache:
            env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(ROOT)}
            env.pop("EVDOWN_EAGER", None)
            for state in ("cold", "warm"):
                done = subprocess.run([sys.executable, __file__, "--one-process"], env=env,
                                      capture_output=True, text=True, check=True)
                found[state].append(json.loads(done.stdout))
    print(f"| first call in a process | cold cache ({args.runs} runs) | warm cache |")
    print("|---|---|---|")
    for step in [*STEPS, "all but import numba"]:
        cells = []
        for state in ("cold", "warm"):
            values = [sum(v for k, v in run.items() if k != "import numba")
                      if step.startswith("all") else run[step] for run in found[state]]
            cells.append(f"{min(values):.2f}-{max(values):.2f} s")
        print(f"| {step} | {cells[0]} | {cells[1]} |")
    print(f"\nload average: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
