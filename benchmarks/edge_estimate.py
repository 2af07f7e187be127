"""What reading Tonic's records in place would save the fastest methods: an estimate for a decision.

Issue 38's goal 2 asks Downsample, EventFunnelling and EventCount for a quarter of the floor's
rate in the live replay. The floor (:mod:`evdown_torch.bench.floor`) reads the chunk's ``x``
and ``y`` fields where they lie. A method reads the chunk into the kernels' columns (int64
``x``, ``y`` and ``t``, bool ``p``: :mod:`evdown_torch.transforms.functional.compiled.columns`),
runs its loop and writes the result into a new structured array: for Downsample and EventCount
the read and the write take half the chunk or more (docs/benchmarks.md, "Third session of
2026-12-05").

This script times, on the replay's chunks (the synthetic gesture recording retimed to 25 M
events/s, 10 ms chunks, factor 4, one thread), beside the floor and the package's sessions:

* ``records Downsample``: one compiled pass from the chunk's records to the output's (the
  coordinates' range and the time order checked, the coordinates shifted, every field
  written);
* ``int32 columns Downsample``: the package's three passes (read, shift, write) with int32
  coordinate columns in place of int64 ones;
* ``records EventCount``: the package's own EventCount loop given the record fields in place
  (strided int16 and bool views), the time order checked by a loop of its own, and the
  crossings written into the output's records;
* ``records EventFunnelling``: the package's funnelling loop given the record fields in place
  likewise, with the session's memory of the last instant's kept events (as
  :func:`~evdown_torch.transforms.functional.funnelling.last_instant` keeps them).

Every variant's output is checked, chunk by chunk, to be the package session's, byte for
byte (the script stops with an error otherwise). Nothing here is part of the package: the
variants leave out what a real path would also need (other factors and dtypes, float
timestamps, the errors' messages, the eager kernels' twins), so their figures bound such a
path's cost from below.

Run: ``python benchmarks/edge_estimate.py [--events 13000000] [--chunks 50]``.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from evdown_torch.bench.estimates import estimate_replay
from evdown_torch.bench.floor import RegionFloor
from evdown_torch.events import DVS_DTYPE
from evdown_torch.transforms.registry import make_method

try:
    import numba
except ImportError:  # pragma: no cover - depends on the machine
    numba = None

SENSOR = (128, 128, 2)
FACTOR = 4
SHIFT = 2  # log2(FACTOR)
REGIONS_WIDE = SENSOR[0] // FACTOR


def compile_loops() -> dict:
    """The variants' loops, compiled (Numba's ``njit``)."""
    if numba is None:
        raise RuntimeError("the compiled loops need numba (pip install numba)")

    @numba.njit(nogil=True)
    def records_downsample(x, y, t, p, width, height, last_t, shift, ox, oy, ot, op):
        outside = 0
        unordered = 0
        previous = last_t
        for i in range(x.shape[0]):
            xi, yi, ti = np.int64(x[i]), np.int64(y[i]), t[i]
            outside += (xi < 0) | (xi >= width) | (yi < 0) | (yi >= height)
            unordered += ti < previous
            previous = ti
            ox[i], oy[i], ot[i], op[i] = xi >> shift, yi >> shift, ti, p[i]
        return outside, unordered

    @numba.njit(nogil=True)
    def unordered_from(t, last_t):
        unordered = 0
        previous = last_t
        for i in range(t.shape[0]):
            unordered += t[i] < previous
            previous = t[i]
        return unordered

    return {"records_downsample": records_downsample, "unordered_from": unordered_from}


class _Columns:
    """Columns reused from chunk to chunk, as the package's scratch columns are."""

    def __init__(self) -> None:
        self.kept: dict[str, np.ndarray] = {}

    def __call__(self, name: str, n: int, dtype: type) -> np.ndarray:
        column = self.kept.get(name)
        if column is None or column.shape[0] < n:
            column = self.kept[name] = np.empty(2 * n + 16, dtype)
        return column[:n]


def _variants(loops: dict) -> dict:
    """Each variant as a session: a call per chunk returning its structured output.

    Beside the one pass of ``records Downsample``, they run the package's own loops: the
    read and write of :mod:`~evdown_torch.transforms.functional.compiled.columns`,
    Downsample's, EventCount's and the funnelling loop.
    """
    from evdown_torch.transforms.functional.compiled.columns import _read_loop, _write_loop
    from evdown_torch.transforms.functional.compiled.downsample import _downsample_loop
    from evdown_torch.transforms.functional.compiled.event_count import _event_count_loop
    from evdown_torch.transforms.functional.compiled.funnelling import _funnel_loop
    from evdown_torch.transforms.functional.compiled.regions import region_tables

    columns = _Columns()
    last = {"records Downsample": -(2**62), "records EventCount": -(2**62),
            "records EventFunnelling": -(2**62)}

    def records_downsample(chunk: np.ndarray) -> np.ndarray:
        out = np.empty(len(chunk), DVS_DTYPE)
        outside, unordered = loops["records_downsample"](
            chunk["x"], chunk["y"], chunk["t"], chunk["p"], SENSOR[0], SENSOR[1],
            last["records Downsample"], SHIFT, out["x"], out["y"], out["t"], out["p"])
        if outside or unordered:
            raise ValueError("an event outside the sensor or out of time order")
        last["records Downsample"] = int(chunk["t"][-1])
        return out

    def narrow_downsample(chunk: np.ndarray) -> np.ndarray:
        n = len(chunk)
        x, y = columns("x", n, np.int32), columns("y", n, np.int32)
        t, p = columns("t", n, np.int64), columns("p", n, np.bool_)
        x_lo, x_hi, y_lo, y_hi, _, in_order, *_ = _read_loop(
            chunk["x"], chunk["y"], chunk["t"], chunk["p"], False, x, y, t, p)
        if x_lo < 0 or x_hi >= SENSOR[0] or y_lo < 0 or y_hi >= SENSOR[1] or not in_order:
            raise ValueError("an event outside the sensor or out of time order")
        out_x, out_y = columns("out x", n, np.int32), columns("out y", n, np.int32)
        _downsample_loop(x, y, FACTOR, FACTOR, column, row, SHIFT, SHIFT, out_x, out_y)
        out_t, out_p = columns("out t", n, np.int64), columns("out p", n, np.bool_)
        out_t[:], out_p[:] = t, p  # a step's result has columns of its own, as the package's
        out = np.empty(n, DVS_DTYPE)
        _write_loop(out_x, out_y, out_t, out_p, 0, out["x"], out["y"], out["t"], out["p"])
        return out

    # EventCount at its default threshold 1 on 4x4 regions: levels every 16 (a * n_r), at most
    # one crossing an event.
    column, row = region_tables((FACTOR, FACTOR), REGIONS_WIDE, REGIONS_WIDE)
    regions = REGIONS_WIDE * REGIONS_WIDE
    level_step = np.full(regions, FACTOR * FACTOR, np.int64)
    level_sum, reference = np.zeros(regions, np.int64), np.zeros(regions, np.int64)

    def records_event_count(chunk: np.ndarray) -> np.ndarray:
        n = len(chunk)
        if loops["unordered_from"](chunk["t"], last["records EventCount"]):
            raise ValueError("an event out of time order")
        out_x, out_y = columns("ec x", n, np.int64), columns("ec y", n, np.int64)
        source, on = columns("ec source", n, np.int64), columns("ec on", n, np.bool_)
        done, k = _event_count_loop(
            chunk["x"], chunk["y"], chunk["p"], column, row, SHIFT, SHIFT, REGIONS_WIDE,
            np.array([n], np.int64), 0, level_step, 1, level_sum, reference, 0, 0, 1,
            out_x, out_y, source, on, False)
        if done != n:
            raise ValueError("an event outside the sensor")
        last["records EventCount"] = int(chunk["t"][-1])
        out = np.empty(k, DVS_DTYPE)
        _write_loop(out_x[:k], out_y[:k], np.take(chunk["t"], source[:k]), on[:k], 0, out["x"],
                    out["y"], out["t"], out["p"])
        return out

    seen: list[np.ndarray] = []  # the kept events at the latest instant so far (records)
    no_index = np.empty(0, np.int64)

    def records_funnelling(chunk: np.ndarray) -> np.ndarray:
        n = len(chunk)
        if loops["unordered_from"](chunk["t"], last["records EventFunnelling"]):
            raise ValueError("an event out of time order")
        kept_in = np.full(2 * regions, -1, np.int64)
        if seen and chunk["t"][0] <= seen[0]["t"][-1]:  # the first run shares seen's instant
            kept_in[(seen[0]["y"].astype(np.int64) * REGIONS_WIDE + seen[0]["x"]) * 2
                    + (seen[0]["p"] > 0)] = 0
        out_x, out_y = columns("ef x", n, np.int64), columns("ef y", n, np.int64)
        out_t, out_p = columns("ef t", n, np.int64), columns("ef p", n, np.bool_)
        k = _funnel_loop(chunk["x"], chunk["y"], chunk["t"], chunk["p"], column, row, SHIFT,
                         SHIFT, REGIONS_WIDE, np.array([n], np.int64), kept_in, no_index,
                         out_x, out_y, out_t, out_p)
        if k < 0:
            raise ValueError("an event outside the sensor")
        last["records EventFunnelling"] = int(chunk["t"][-1])
        out = np.empty(k, DVS_DTYPE)
        _write_loop(out_x[:k], out_y[:k], out_t[:k], out_p[:k], 0, out["x"], out["y"],
                    out["t"], out["p"])
        if k:
            tail = out[np.searchsorted(out["t"], out["t"][-1], side="left"):]
            if tail is out and seen and seen[0]["t"][-1] == out["t"][-1]:
                tail = np.concatenate([seen[0], tail])
            seen[:] = [tail.copy()]
        return out

    return {"records Downsample": records_downsample,
            "int32 columns Downsample": narrow_downsample,
            "records EventCount": records_event_count,
            "records EventFunnelling": records_funnelling}


def main(argv: list[str] | None = None) -> int:
    replay = estimate_replay(argv, __doc__, compiled=numba is not None, sensor_size=SENSOR)
    if replay is None:
        return 2
    stream, bounds, last = replay
    variants = _variants(compile_loops())
    sessions = {"floor": RegionFloor(SENSOR, FACTOR).session(),
                "Downsample session (package)": make_method("downsample", SENSOR,
                                                            FACTOR).session(),
                "records Downsample": variants["records Downsample"],
                "int32 columns Downsample": variants["int32 columns Downsample"],
                "EventCount session (package)": make_method("event_count", SENSOR,
                                                            FACTOR).session(),
                "records EventCount": variants["records EventCount"],
                "EventFunnelling session (package)": make_method("funnelling", SENSOR,
                                                                 FACTOR).session(),
                "records EventFunnelling": variants["records EventFunnelling"]}
    peers = {"records Downsample": "Downsample session (package)",
             "int32 columns Downsample": "Downsample session (package)",
             "records EventCount": "EventCount session (package)",
             "records EventFunnelling": "EventFunnelling session (package)"}
    seconds: dict[str, list[float]] = {name: [] for name in sessions}
    events_out = dict.fromkeys(sessions, 0)
    names = list(sessions)
    for k in range(last + 1):  # chunk 0 warms up (and compiles)
        chunk = stream[int(bounds[k]):int(bounds[k + 1])]
        outputs = {}
        for name in names if k % 2 == 0 else names[::-1]:  # each order half the chunks
            start = time.perf_counter()
            outputs[name] = sessions[name](chunk)
            if k:
                seconds[name].append(time.perf_counter() - start)
                events_out[name] += len(outputs[name])
        for name, peer in peers.items():
            if outputs[name].tobytes() != outputs[peer].tobytes():
                raise RuntimeError(f"{name} differs from {peer} on chunk {k}")
    floor_p99 = float(np.percentile(seconds["floor"], 99))
    print(f"{last} timed 10 ms chunks at 25 M events/s, factor {FACTOR}, one thread; "
          "every variant's output is its package session's, byte for byte")
    print("| variant | median (ms) | p99 (ms) | x floor (p99s) | events out |")
    print("|---|---|---|---|---|")
    for name, times in seconds.items():
        p99 = float(np.percentile(times, 99))
        print(f"| {name} | {statistics.median(times) * 1e3:.3f} | {p99 * 1e3:.3f} | "
              f"{floor_p99 / p99:.3f} | {events_out[name]:,} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
