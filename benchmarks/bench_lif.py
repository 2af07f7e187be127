"""LIFPooling speed and memory, one thread.

1. Speed: a DVS-Gesture-like stream on a 128x128 sensor (two moving "hands" plus uniform
   background noise, ~300k events/s, timestamps in microseconds), factor 4, dt = 1 ms,
   default settings: events/s, median of several runs (Tonic structured array in and out).
2. Memory: a long 1280x720 recording (60 s by default, same kind of stream), factor 4,
   dt = 1 ms: peak resident memory of the transform beyond its input, measured in a child
   process as the peak resident set size during the call (Linux ``VmHWM``, reset just before
   it) minus the resident size before it.

Run: ``python benchmarks/bench_lif.py [--events N] [--repeats R] [--long-seconds S]``.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("p", bool), ("t", np.int64)])


def gesture_stream(
    n: int,
    sensor=(128, 128),
    rate: float = 300_000.0,
    noise: float = 0.2,
    seed: int = 0,
    t0: int = 0,
) -> np.ndarray:
    """``n`` events: two blobs circling the sensor (ON at the leading edge, OFF behind) plus noise.

    Args:
        n: number of events.
        sensor: ``(W, H)``.
        rate: events per second (timestamps in microseconds).
        noise: fraction of uniform background events.
        seed: NumPy seed.
        t0: first possible timestamp.
    """
    rng = np.random.default_rng(seed)
    w, h = sensor
    t = t0 + np.sort(rng.integers(0, int(n / rate * 1e6), n))
    is_noise = rng.random(n) < noise
    hand = rng.integers(0, 2, n)
    phase = 2 * np.pi * t / 1.5e6 + np.pi * hand  # one turn per 1.5 s
    cx = w / 2 + 0.3 * w * np.cos(phase)
    cy = h / 2 + 0.3 * h * np.sin(phase) * (1 - 2 * hand)
    radius = 0.08 * min(w, h)
    angle = rng.random(n) * 2 * np.pi
    r = radius * np.sqrt(rng.random(n))
    x = cx + r * np.cos(angle)
    y = cy + r * np.sin(angle)
    # Leading half of the blob (along its velocity) brightens: ON; trailing half: OFF.
    vx, vy = -np.sin(phase), np.cos(phase) * (1 - 2 * hand)
    on = (np.cos(angle) * vx + np.sin(angle) * vy) > 0
    x = np.where(is_noise, rng.integers(0, w, n), np.clip(np.round(x), 0, w - 1))
    y = np.where(is_noise, rng.integers(0, h, n), np.clip(np.round(y), 0, h - 1))
    on = np.where(is_noise, rng.random(n) < 0.5, on)
    out = np.empty(n, dtype=DTYPE)
    out["x"], out["y"], out["p"], out["t"] = x, y, on, t
    return out


def median_seconds(fn, data, repeats: int) -> float:
    fn(data)  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn(data)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _memory_kib(field: str) -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def _reset_peak() -> int:
    """Reset the peak resident size (Linux ``VmHWM``) to the current one and return it, bytes."""
    with open("/proc/self/clear_refs", "w") as refs:
        refs.write("5")
    return _memory_kib("VmRSS") * 1024


def peak_memory_child(seconds: float, rate: float) -> None:
    """Child process: print events, input bytes, RSS before, peak RSS of the call, ..."""
    from evdown_torch import LIFPooling
    from evdown_torch.events import to_events

    torch.set_num_threads(1)
    per_second = int(rate)
    data = np.concatenate([
        gesture_stream(per_second, sensor=(1280, 720), rate=rate, seed=s, t0=s * 1_000_000)
        for s in range(int(seconds))
    ])
    pool = LIFPooling((1280, 720, 2), factor=4)
    before = _reset_peak()
    start = time.perf_counter()
    out = pool(data)
    elapsed = time.perf_counter() - start
    peak = _memory_kib("VmHWM") * 1024
    n_out = len(out)
    del out
    events, _ = to_events(data, pool.sensor_size)  # the kernel alone, after the conversion
    kernel_before = _reset_peak()
    pool.kernel(events)
    kernel_peak = _memory_kib("VmHWM") * 1024
    print(len(data), data.nbytes, before, peak, n_out, elapsed, kernel_peak - kernel_before)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--long-seconds", type=float, default=60.0)
    parser.add_argument("--long-rate", type=float, default=1_000_000.0)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        peak_memory_child(args.long_seconds, args.long_rate)
        return
    from evdown_torch import Downsample, LIFPooling

    torch.set_num_threads(1)
    sensor = (128, 128, 2)
    data = gesture_stream(args.events)
    duration = (data["t"][-1] - data["t"][0]) * 1e-6
    print(f"{args.events} events over {duration:.2f} s on 128x128 (gesture-like), factor 4, "
          f"one thread, median of {args.repeats}")
    print(f"{'method':<34} {'seconds':>9} {'Mev/s':>8} {'out/in':>8}")
    rows = [
        ("Downsample", Downsample(sensor, factor=4)),
        ("LIFPooling (defaults)", LIFPooling(sensor, factor=4)),
        ("LIFPooling (w_inh=0.3, zero reset)",
         LIFPooling(sensor, factor=4, mutual_inhibition=0.3, reset_mechanism="zero")),
        ("LIFPooling (weight=1.5: dense out)", LIFPooling(sensor, factor=4, weight=1.5)),
    ]
    for name, fn in rows:
        s = median_seconds(fn, data, args.repeats)
        ratio = len(fn(data)) / len(data)
        print(f"{name:<34} {s:9.4f} {args.events / s / 1e6:8.2f} {ratio:8.4f}")

    if args.long_seconds > 0:
        cmd = [sys.executable, __file__, "--child", "--long-seconds", str(args.long_seconds),
               "--long-rate", str(args.long_rate)]
        n, nbytes, before, peak, n_out, elapsed, kernel = (
            float(v) for v in subprocess.check_output(cmd, text=True).split()
        )
        mib = 2**20
        print(f"\nlong recording: 1280x720, {args.long_seconds:.0f} s, {n:.0f} events "
              f"({nbytes / mib:.0f} MiB structured array), factor 4, dt = 1 ms, defaults")
        print(f"  whole call: RSS {before / mib:.0f} MiB before, peak {peak / mib:.0f} MiB "
              f"(+{(peak - before) / mib:.0f} MiB = {(peak - before) / n:.1f} bytes/event), "
              f"{n_out:.0f} output events, {elapsed:.1f} s ({n / elapsed / 1e6:.2f} Mev/s)")
        print(f"  kernel alone (after the conversion to Events): peak +{kernel / mib:.0f} MiB "
              f"({kernel / n:.1f} bytes/event)")


if __name__ == "__main__":
    main()
