"""A chip's input budget end to end: choose a method, calibrate to a peak, limit, measure latency.

The question: a DVS346 (346x260) camera at up to ~10 M events/s feeds a chip that takes 64x64
input and at most 500 k events/s, causally, within a few milliseconds. A synthetic DVS346
recording replayed at ``--rate`` events/s stands in for the camera (seeded: the same events on
every machine). The script

1. chooses EventCount at factor 6 (58x44 fits 64x64; causal: no algorithmic delay);
2. shows that a *mean* rate budget of 500 k events/s leaves the busiest millisecond far above
   it, then calibrates to the *peak* (at most 500 events in any 1 ms: ``peak=500000/1ms``);
3. puts a RateLimiter (a token bucket of 500 per 1 ms) after it, the hard cap for what the
   calibration never saw: nothing to drop after the peak calibration, the bursts after the
   mean-only one (it counts its drops);
4. replays the chain live in 1, 2 and 10 ms chunks and prints its latency budget: algorithmic
   delay + chunk + 99th percentile of the processing time (on this machine, now).

    python examples/chip_budget.py                          # 1 s of stream at 9.5 M events/s
    python examples/chip_budget.py --duration-ms 300 --rate 5e6
"""

import argparse

import numpy as np
import torch

from evdown_torch import Chain, EventCount, RateLimiter
from evdown_torch.bench.realtime import replay, retime
from evdown_torch.synthetic import SyntheticGestures
from evdown_torch.transforms import BudgetTarget, calibrate, window_rates

SENSOR = (346, 260, 2)          # DVS346 / DAVIS346
CHIP_EVENTS, CHIP_WINDOW_US = 500, 1_000   # 500 events per 1 ms: 500 k events/s at peak


def recording(duration_ms: int, rate: float) -> np.ndarray:
    """A synthetic DVS346 gesture, replayed at ``rate`` events per second."""
    data = SyntheticGestures(train=False, samples_per_class=1, sensor_size=SENSOR,
                             duration_us=duration_ms * 1000)
    return retime(data[0][0], rate)[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-ms", type=int, default=1000)
    parser.add_argument("--rate", type=float, default=9.5e6, help="replayed input events/s")
    args = parser.parse_args()
    torch.set_num_threads(1)            # small live chunks run best on one thread

    seen = recording(args.duration_ms, args.rate)
    print(f"DVS346 recording: {len(seen):,} events at {args.rate / 1e6:g} M events/s")

    # 1. Choose: causal, two integers per output pixel, a threshold that sets the budget.
    method = EventCount(SENSOR, factor=6)
    print(f"EventCount at factor 6: {SENSOR[:2]} -> {method.output_sensor_size[:2]}")

    # 2. A mean budget is not a peak budget.
    mean_only = calibrate(method, [seen], BudgetTarget.rate(CHIP_EVENTS * 1e3))
    rates = window_rates([mean_only(seen)], CHIP_WINDOW_US)
    print(f"calibrated to a mean of 500 k events/s: {rates.describe()}")
    assert rates.per_second(rates.peak) > CHIP_EVENTS * 1e3, "the peak breaks the cap"

    peak = calibrate(method, [seen], BudgetTarget.peak(CHIP_EVENTS, window=CHIP_WINDOW_US))
    rates = window_rates([peak(seen)], CHIP_WINDOW_US)
    print(f"calibrated to peak=500000/1ms (threshold {peak.threshold:.4g}): {rates.describe()}")
    assert rates.peak <= CHIP_EVENTS

    # 3. The hard cap: a token bucket after the method (the chip's FIFO of 500, drained at
    # 500 per ms), for what no calibration saw. After the peak calibration it drops nothing;
    # after the mean-only one it cuts the bursts, and its state counts what it dropped.
    limiter = RateLimiter(CHIP_EVENTS, CHIP_WINDOW_US, sensor_size=method.output_sensor_size)
    chip = Chain(peak, limiter)
    assert len(chip(seen)) == len(peak(seen)), "within the peak: the limiter drops nothing"
    session = Chain(mean_only, limiter).session()
    out = session(seen)
    dropped = session.state[1].dropped                      # the limiter's own count
    out = np.concatenate([out, session.flush()])
    print(f"mean-only calibration, then the limiter: {len(out) + dropped:,} events in, "
          f"{dropped:,} dropped; {window_rates([out], CHIP_WINDOW_US).describe()}")
    assert np.array_equal(out, limiter(mean_only(seen)))

    # 4. Latency, all of it: algorithmic delay + chunk + p99 of the processing time.
    for chunk_us in (1_000, 2_000, 10_000):
        result = replay(chip, seen, chunk_us=chunk_us, rate=args.rate, label="chip")
        if result.p99_s is None:
            print(f"{chunk_us / 1e3:g} ms chunks: the stream is too short to time any")
            continue
        budget = result.latency_budget_s
        total = "falls behind" if budget is None else f"{budget * 1e3:.2f} ms"
        chunks = f"{result.chunks} chunk" + "s" * (result.chunks != 1)
        print(f"{chunk_us / 1e3:g} ms chunks: delay 0 + chunk {chunk_us / 1e3:g} ms + p99 "
              f"{result.p99_s * 1e3:.2f} ms (over {chunks}) = latency budget {total}")


if __name__ == "__main__":
    main()
