"""Downscale a live event stream chunk by chunk with a session, as a camera delivers it.

A synthetic 128x128 gesture cut into packets of a few milliseconds stands in for a camera's
driver. Two sessions run side by side: ``EventCount`` (causal: a packet's output comes out with
it) and ``LinearEstimation`` with a bounded delay ``max_delay`` (an event comes out once the
stream has gone ``max_delay`` past it). Each session's concatenated output equals the
transform applied to the whole recording.

    python examples/live_stream.py                    # 2 s of stream in 10 ms packets
    python examples/live_stream.py --duration-ms 300 --packet-ms 5
"""

import argparse
import time

import numpy as np
import torch

from evdown_torch import EventCount, LinearEstimation
from evdown_torch.synthetic import SyntheticGestures


def packets(events: np.ndarray, packet_us: int):
    """Consecutive packets of ``packet_us`` of stream time (what a camera driver hands over)."""
    edges = np.arange(events["t"][0] + packet_us, events["t"][-1] + 1, packet_us)
    return np.split(events, np.searchsorted(events["t"], edges))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-ms", type=int, default=2000)
    parser.add_argument("--packet-ms", type=float, default=10.0)
    parser.add_argument("--max-delay-us", type=int, default=1000)
    args = parser.parse_args()
    torch.set_num_threads(1)        # small per-packet calls run best on one thread

    recording, label = SyntheticGestures(train=False, samples_per_class=1,
                                         duration_us=args.duration_ms * 1000)[0]
    sensor = (128, 128, 2)
    methods = {
        "EventCount": EventCount(sensor, factor=4, threshold=0.5),
        "LinearEstimation": LinearEstimation(sensor, factor=4, threshold=0.5,
                                             max_delay=args.max_delay_us),
    }
    stream = packets(recording, int(args.packet_ms * 1000))
    empty = sum(packet.size == 0 for packet in stream)
    print(f"{recording.size} events in {len(stream)} packets of {args.packet_ms} ms "
          f"({empty} empty)")

    for name, down in methods.items():
        session = down.session()
        outputs, seconds, delays = [], [], []
        for packet in stream:                       # in time order; empty packets are fine
            start = time.perf_counter()
            out = session(packet)                   # the events this packet decides
            seconds.append(time.perf_counter() - start)
            if out.size and packet.size:
                delays.append(int(packet["t"][-1] - out["t"].min()))
            outputs.append(out)
        outputs.append(session.flush())             # what only the end of the stream decides
        live = np.concatenate(outputs)
        assert np.array_equal(live, down(recording)), "a session equals the whole-stream call"
        print(f"{name}: {live.size} events out on a {down.output_sensor_size} sensor; "
              f"median {1e3 * np.median(seconds):.2f} ms per packet; "
              f"an output event at most {max(delays, default=0)} us older than its packet's end")


if __name__ == "__main__":
    main()
