"""What the first compiled call of a process costs, with a cold and with a warm Numba cache.

Each run starts two fresh processes sharing a new, empty ``NUMBA_CACHE_DIR``: the first finds
the cache cold (it compiles every loop and fills the cache), the second warm. Each process
imports ``evdown_torch`` (which imports no Numba), then times ``import numba`` and the first
call of each method with a compiled loop, in order, on 100 events (16x16, factor 4), and the
replay's floor; before them, a Tonic structured array read and written back (its column loops,
which every method's first call would otherwise pay). Prints one Markdown table of the ranges
over the runs (``docs/benchmarks.md``, "Compiled CPU kernels").

Also names the package's loops that a run compiled a second time for a constant argument
(a literal type; expected: none).

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
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

ROOT = Path(__file__).resolve().parents[1]

STEPS = ["import numba", "Tonic array in and out", "EventCount", "Downsample", "EventFunnelling",
         "TemporalFunnelling", "PhotocurrentPooling", "LIFPooling", "LinearEstimation",
         "CubicEstimation", "LinearEstimation session (max_delay)", "DensitySubsampling",
         "DensitySubsampling, 640x480 (patches only)", "PoissonSubsampling", "floor"]


def one_process() -> tuple[dict[str, float], list[str]]:
    """The first calls of this process, in seconds, and the loops compiled twice.

    The second item names the package's loops compiled for a constant argument
    (:func:`_literal_copies`). Run in a fresh process.
    """
    import numpy as np

    from evdown_torch import (
        CubicEstimation,
        DensitySubsampling,
        Downsample,
        EventCount,
        EventFunnelling,
        LIFPooling,
        LinearEstimation,
        PhotocurrentPooling,
        PoissonSubsampling,
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
        # each estimator's curve has a window loop of its own (the shared helpers compile once)
        "LinearEstimation": LinearEstimation((16, 16, 2), 4, threshold=0.25),
        "CubicEstimation": CubicEstimation((16, 16, 2), 4, threshold=0.25),
        # a bounded-delay session: its steps compile the ramps and the state they make
        "LinearEstimation session (max_delay)": lambda ev: _two_chunks(
            LinearEstimation((16, 16, 2), 4, threshold=0.25, max_delay=10).session(), ev),
        # budgets that drop events: the subsamplers' draws and decision loops
        "DensitySubsampling": DensitySubsampling((16, 16, 2), 4, tau=20.0, s=0.3),
        # a sensor the events' patches cover less of: the counts of the patches only
        "DensitySubsampling, 640x480 (patches only)": DensitySubsampling(
            (640, 480, 2), 4, tau=20.0, s=0.3),
        "PoissonSubsampling": PoissonSubsampling((16, 16, 2), 4, window=10, alpha=0.3),
        "floor": RegionFloor((16, 16, 2), 4).session(),
    }
    from numba.core import types
    from numba.core.event import install_recorder

    with install_recorder("numba:compile") as recorder:
        for name, call in calls.items():
            start = time.perf_counter()
            call(ev)
            seconds[name] = time.perf_counter() - start
    return seconds, sorted(_literal_copies(recorder.buffer, types.Literal))


def _literal_copies(compiles: list[tuple[float, Any]], literal: type) -> set[str]:
    """The package's loops compiled for a constant argument (``Literal[int](0)``, ...).

    Numba types a call whose argument is a constant, such as a counter's first value, with
    that constant's literal type, and compiles a copy of the callee for it beside the one for
    ``int64``: first-call time for nothing (``np.int64(0)`` gives the counter its type).
    """
    from evdown_torch.transforms.functional.compiled._numba import written_name

    found = set()
    for _, event in compiles:
        function = getattr(event.data.get("dispatcher"), "py_func", None)
        args = event.data.get("args") or ()
        if (event.is_start and function is not None
                and function.__module__.startswith("evdown_torch")
                and any(isinstance(arg, literal) for arg in args)):
            found.add(f"{function.__module__}.{written_name(function)}")
    return found


def _two_chunks(session: Callable[[np.ndarray], object], ev: np.ndarray) -> None:
    session(ev[:50])
    session(ev[50:])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--one-process", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one_process:
        seconds, copies = one_process()
        print(json.dumps({"seconds": seconds, "literal": copies}))
        return 0
    found: dict[str, list[dict[str, float]]] = {"cold": [], "warm": []}
    compiled_twice: set[str] = set()
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory() as cache:
            env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(ROOT)}
            env.pop("EVDOWN_EAGER", None)
            for state in ("cold", "warm"):
                done = subprocess.run([sys.executable, __file__, "--one-process"], env=env,
                                      capture_output=True, text=True, check=True)
                result = json.loads(done.stdout)
                found[state].append(result["seconds"])
                compiled_twice.update(result["literal"])
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
    print("loops compiled again for a constant argument: "
          + (", ".join(sorted(compiled_twice)) if compiled_twice else "none"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
