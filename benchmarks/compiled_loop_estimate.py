"""What a compiled per-event loop would cost in the live replay: an estimate for a decision.

Written when the package's kernels were all vectorised eager torch: issue 29's live goals
for PhotocurrentPooling and the estimators are out of their reach
(``benchmarks/bench_realtime_floor.py``); a compiled kernel is the other way. This script
estimates what one would cost, with Numba (the ``compiled`` and ``all`` extras install it;
the package's own compiled loops, since issue 38, are in
``evdown_torch/transforms/functional/compiled/``; nothing here is part of the package):
one sequential loop over the events of each chunk of the live replay (the synthetic
gesture recording retimed to 25 M events/s, 10 ms chunks, factor 4, one thread), beside the
package's own sessions on the same chunks.

* EventCount's loop is exact for threshold 1 (integer region sums against multiples of
  ``n_r``), and its event count is checked against the package's.
* PhotocurrentPooling's loops keep a float64 running sum of ``exp(c * L)`` per region (the
  package decides on exact fixed-point sums and snaps values within ``1e-9`` of a level;
  that would cost more), either taking a logarithm per event or comparing the sum with the
  two levels around ``q``. Their event counts are printed beside the package's: close, not
  equal, since the arithmetic is not the contract's.

So the figures bound a compiled kernel's cost from below; they are no implementation.

Run: ``python benchmarks/compiled_loop_estimate.py [--events 13000000] [--chunks 50]``.
"""

from __future__ import annotations

import math
import statistics
import time

import numpy as np

from evdown_torch.bench.estimates import estimate_replay
from evdown_torch.transforms.registry import make_method

try:
    import numba
except ImportError:  # pragma: no cover - depends on the machine
    numba = None

SENSOR = (128, 128, 2)
FACTOR = 4
CONTRAST = 0.2  # PhotocurrentPooling's default contrast (and threshold)


def compile_loops() -> dict:
    """The three loops, compiled (Numba's ``njit``)."""
    if numba is None:
        raise RuntimeError("the compiled loops need numba (pip install numba)")

    @numba.njit(nogil=True)
    def event_count(x, y, p, total, q, width, n_r, out_on):  # pragma: no cover - compiled
        k = 0
        for i in range(x.shape[0]):
            r = (y[i] // FACTOR) * width + x[i] // FACTOR
            total[r] += 1 if p[i] else -1
            while total[r] >= (q[r] + 1) * n_r:
                q[r] += 1
                out_on[k] = True
                k += 1
            while total[r] <= (q[r] - 1) * n_r:
                q[r] -= 1
                out_on[k] = False
                k += 1
        return k

    @numba.njit(nogil=True)
    def photocurrent_log(x, y, p, level, total, q, width, n_r, table, middle,
                         out_on):  # pragma: no cover - compiled
        k = 0
        log_n = math.log(n_r)
        for i in range(x.shape[0]):
            pixel = y[i] * SENSOR[0] + x[i]
            r = (y[i] // FACTOR) * width + x[i] // FACTOR
            before = level[pixel]
            after = before + (1 if p[i] else -1)
            total[r] += table[after + middle] - table[before + middle]
            level[pixel] = after
            u = (math.log(total[r]) - log_n) / CONTRAST
            while u >= q[r] + 1:
                q[r] += 1
                out_on[k] = True
                k += 1
            while u <= q[r] - 1:
                q[r] -= 1
                out_on[k] = False
                k += 1
        return k

    @numba.njit(nogil=True)
    def photocurrent_bounds(x, y, p, level, total, q, high, low, width, n_r, table, middle,
                            out_on):  # pragma: no cover - compiled
        k = 0
        for i in range(x.shape[0]):
            pixel = y[i] * SENSOR[0] + x[i]
            r = (y[i] // FACTOR) * width + x[i] // FACTOR
            before = level[pixel]
            after = before + (1 if p[i] else -1)
            value = total[r] + table[after + middle] - table[before + middle]
            total[r] = value
            level[pixel] = after
            if value >= high[r] or value <= low[r]:
                while value >= high[r]:
                    q[r] += 1
                    out_on[k] = True
                    k += 1
                    high[r] = n_r * math.exp(CONTRAST * (q[r] + 1))
                    low[r] = n_r * math.exp(CONTRAST * (q[r] - 1))
                while value <= low[r]:
                    q[r] -= 1
                    out_on[k] = False
                    k += 1
                    high[r] = n_r * math.exp(CONTRAST * (q[r] + 1))
                    low[r] = n_r * math.exp(CONTRAST * (q[r] - 1))
        return k

    return {"event_count_loop": event_count, "photocurrent_log": photocurrent_log,
            "photocurrent_bounds": photocurrent_bounds}


def main(argv: list[str] | None = None) -> int:
    replay = estimate_replay(argv, __doc__, compiled=numba is not None, sensor_size=SENSOR)
    if replay is None:
        return 2
    stream, bounds, last = replay
    x, y = stream["x"].astype(np.int64), stream["y"].astype(np.int64)
    p = stream["p"].astype(np.bool_)
    width = SENSOR[0] // FACTOR
    regions, n_r = width * (SENSOR[1] // FACTOR), FACTOR * FACTOR
    middle = 3000  # levels -3000..3000: exp(0.2 * 3000) is still a float64
    table = np.exp(CONTRAST * (np.arange(2 * middle + 1) - middle))
    out_on = np.empty(4 * len(stream) + 16, dtype=np.bool_)
    loops = compile_loops()
    states = {
        "event_count_loop": (np.zeros(regions, np.int64), np.zeros(regions, np.int64)),
        "photocurrent_log": (np.zeros(SENSOR[0] * SENSOR[1], np.int64),
                             np.full(regions, float(n_r)), np.zeros(regions, np.int64)),
        "photocurrent_bounds": (np.zeros(SENSOR[0] * SENSOR[1], np.int64),
                                np.full(regions, float(n_r)), np.zeros(regions, np.int64),
                                np.full(regions, n_r * math.exp(CONTRAST)),
                                np.full(regions, n_r * math.exp(-CONTRAST))),
    }

    def run(name: str, lo: int, hi: int) -> int:
        state = states[name]
        if name == "event_count_loop":
            return loops[name](x[lo:hi], y[lo:hi], p[lo:hi], *state, width, n_r, out_on)
        return loops[name](x[lo:hi], y[lo:hi], p[lo:hi], *state, width, float(n_r), table,
                           middle, out_on)

    sessions = {name: make_method(name, SENSOR, FACTOR).session()
                for name in ("event_count", "photocurrent")}
    seconds: dict[str, list[float]] = {name: [] for name in [*loops, *sessions]}
    events_out = dict.fromkeys(seconds, 0)
    for k in range(last + 1):  # chunk 0 warms up (and compiles)
        lo, hi = int(bounds[k]), int(bounds[k + 1])
        for name in seconds:
            start = time.thread_time()
            made = len(sessions[name](stream[lo:hi])) if name in sessions else run(name, lo, hi)
            if k:
                seconds[name].append(time.thread_time() - start)
            events_out[name] += made
    n_events = int(bounds[last + 1] - bounds[1])
    base = sum(seconds["event_count"])
    print(f"{last} chunks, {n_events:,} events; CPU time, one thread\n")
    print("| loop or session | median chunk (ms) | total over EventCount's session "
          "| ns per event | output events (all chunks) |")
    print("|---|---|---|---|---|")
    labels = {"event_count": "EventCount session (package)",
              "photocurrent": "PhotocurrentPooling session (package)",
              "event_count_loop": "compiled EventCount loop",
              "photocurrent_log": "compiled photocurrent loop, a logarithm per event",
              "photocurrent_bounds": "compiled photocurrent loop, sum against two levels"}
    for name, times in seconds.items():
        print(f"| {labels[name]} | {1e3 * statistics.median(times):.2f} | {sum(times) / base:.2f} "
              f"| {1e9 * sum(times) / n_events:.1f} | {events_out[name]:,} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
