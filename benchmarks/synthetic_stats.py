"""Statistics of the synthetic gestures next to DVS128 Gesture's anchors (issue 13).

Run: ``python benchmarks/synthetic_stats.py [--seeds N] [--duration-us D]``. Renders 6 s,
128x128 recordings (by default one per class for each of 2 seeds: 22 recordings, fixed seeds)
on one thread and prints, per recording and summarised:

* events per recording (anchor: DVS128 Gesture about 200k to 400k, the paper's mean 194,398);
* ON share (anchor: varies by recording and lighting; target about 0.4 to 0.6);
* peak / mean event rate in 10 ms bins (target at least 3: idle start and end, pauses,
  acceleration);
* share of events EventFunnelling removes at factor 4 (anchor: the paper's Table 1, 4.1 %;
  target 2 to 6 %);
* lighting and flicker frequency;
* render time, CPU seconds of one thread (target under 0.5 s; a shared machine is noisy, so
  the median is reported).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from evdown_torch import EventFunnelling
from evdown_torch.synthetic import GESTURE_CLASSES, GestureScene, render_events
from evdown_torch.synthetic.dataset import DVS_GESTURE_DTYPE

SENSOR = (128, 128, 2)


def recording_stats(label: int, seed: int, duration_us: int) -> dict:
    """Render one recording and measure it."""
    scene = GestureScene.sample(label, seed, sensor_size=SENSOR, duration_us=duration_us)
    start = time.process_time()
    events = render_events(scene)
    cpu = time.process_time() - start
    n = events.num_events
    bins = torch.bincount(events.t // 10_000, minlength=max(1, duration_us // 10_000))
    array = np.zeros(n, DVS_GESTURE_DTYPE)
    for name in ("x", "y", "t", "p"):
        array[name] = getattr(events, name).numpy()
    funnelled = len(EventFunnelling(SENSOR, factor=4)(array))
    return {
        "label": label, "seed": seed, "events": n,
        "on_share": float(events.p.float().mean()) if n else float("nan"),
        "peak_mean": float(bins.max()) / float(bins.float().mean()) if n else float("nan"),
        "funnel_removed": 1 - funnelled / n if n else float("nan"),
        "lighting": f"{scene.lighting} {scene.flicker_hz:.0f} Hz" if scene.flicker_hz
        else scene.lighting,
        "cpu_s": cpu,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=2, help="recordings per class")
    parser.add_argument("--duration-us", type=int, default=6_000_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = [recording_stats(label, 1000 * k + label, args.duration_us)
            for k in range(args.seeds) for label in range(len(GESTURE_CLASSES))]
    print(f"{'class':<16} {'seed':>5} {'events':>8} {'ON':>6} {'pk/mean':>8} "
          f"{'funnel x4':>9} {'cpu s':>6}  lighting")
    for r in rows:
        print(f"{GESTURE_CLASSES[r['label']][:16]:<16} {r['seed']:>5} {r['events']:>8} "
              f"{r['on_share']:6.3f} {r['peak_mean']:8.2f} {100 * r['funnel_removed']:8.2f}% "
              f"{r['cpu_s']:6.3f}  {r['lighting']}")

    def span(key: str, scale: float = 1.0, fmt: str = ".3f") -> str:
        values = [r[key] * scale for r in rows]
        return (f"{min(values):{fmt}} to {max(values):{fmt}}, mean "
                f"{statistics.mean(values):{fmt}}, median {statistics.median(values):{fmt}}")

    lights = {name: sum(1 for r in rows if r["lighting"].startswith(name))
              for name in ("natural", "fluorescent", "led")}
    print()
    print(f"| statistic ({len(rows)} recordings, {args.duration_us / 1e6:g} s, 128x128) "
          "| synthetic | anchor / target |")
    print("|---|---|---|")
    print(f"| events per recording | {span('events', fmt='.0f')} | DVS128 Gesture about 200k "
          "to 400k (paper's mean 194,398); target mean 190k to 400k |")
    print(f"| ON share | {span('on_share')} | varies by recording; about 0.4 to 0.6 |")
    print(f"| peak / mean rate, 10 ms bins | {span('peak_mean', fmt='.2f')} | at least 3 |")
    print(f"| EventFunnelling x4 removes (%) | {span('funnel_removed', 100, '.2f')} | paper "
          "4.1 %; target 2 to 6 % |")
    print(f"| lighting | {lights} | natural / fluorescent / LED |")
    print(f"| render CPU s (one thread; shared machine, noisy) | {span('cpu_s')} | "
          "under 0.5 s |")


if __name__ == "__main__":
    main()
