"""``evdown preprocess`` on the synthetic gestures: one process against two, and the I/O share.

Run: ``python benchmarks/bench_preprocess.py [--short] [--samples-per-class N]
[--duration-us US] [--method NAME] [--factor F] [--shard-size N] [--json FILE]``.

Each configuration preprocesses the same synthetic dataset into a fresh temporary folder
through :func:`evdown_torch.data.preprocess` (as the command does): ``--workers 1`` works in
this process, ``--workers 2`` in two spawned worker processes (their start-up included), one
torch thread each. Reported per configuration: wall seconds, recordings and events per second,
the speed-up over one process (goal: >= 1.7x on a 2-core machine), and where the workers'
time went: rendering the recordings (the synthetic "read"), downscaling, and writing the
shards with their checksums (the I/O share). Both caches must have the same checksums.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch

from evdown_torch.data import open_source, preprocess

GOAL = 1.7


def run_once(args: argparse.Namespace, workers: int, folder: Path) -> dict:
    source = open_source("synthetic", samples_per_class=args.samples_per_class,
                         duration_us=args.duration_us, sensor_size=tuple(args.sensor_size))
    result = preprocess(source, folder, args.method, args.factor, shard_size=args.shard_size,
                        workers=workers, progress=False)
    busy = result.read_seconds + result.transform_seconds + result.write_seconds
    written = sum(p.stat().st_size for p in folder.glob("shard-*.npy"))
    checksums = {r["shard"]: r["sha256"] for r in result.manifest["shards"]}
    return {
        "workers": workers,
        "seconds": result.seconds,
        "recordings": result.recordings,
        "events_in": result.manifest["counts"]["events_in"],
        "events_out": result.manifest["counts"]["events_out"],
        "bytes_written": written,
        "read_share": result.read_seconds / busy,
        "transform_share": result.transform_seconds / busy,
        "io_share": result.write_seconds / busy,
        "checksums": checksums,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--short", action="store_true",
                        help="a quick check that it works: 2 per class, 0.5 s, 64x64")
    parser.add_argument("--samples-per-class", type=int, default=24)
    parser.add_argument("--duration-us", type=int, default=6_000_000)
    parser.add_argument("--sensor-size", type=int, nargs=3, default=[128, 128, 2])
    parser.add_argument("--method", default="event_count")
    parser.add_argument("--factor", type=int, default=4)
    parser.add_argument("--shard-size", type=int, default=4)
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()
    if args.short:
        args.samples_per_class, args.duration_us, args.sensor_size = 2, 500_000, [64, 64, 2]
    torch.set_num_threads(1)
    rows = []
    for workers in (1, 2):
        with tempfile.TemporaryDirectory() as folder:
            rows.append(run_once(args, workers, Path(folder)))
    if rows[0]["checksums"] != rows[1]["checksums"]:
        raise SystemExit("the two runs wrote different caches")
    n = rows[0]["recordings"]
    print(f"synthetic gestures: {n} recordings of {args.duration_us / 1e6:g} s at "
          f"{args.sensor_size[0]}x{args.sensor_size[1]}, {rows[0]['events_in']} events; "
          f"{args.method} x{args.factor}, {args.shard_size} recordings per shard, "
          f"{rows[0]['bytes_written'] / 1e6:.1f} MB written")
    print("| processes | wall s | recordings/s | M events/s | speed-up | render | downscale "
          "| write (I/O) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        row["speedup"] = rows[0]["seconds"] / row["seconds"]
        print(f"| {row['workers']} | {row['seconds']:.2f} | {n / row['seconds']:.1f} | "
              f"{row['events_in'] / row['seconds'] / 1e6:.2f} | {row['speedup']:.2f}x | "
              f"{row['read_share']:.0%} | {row['transform_share']:.0%} | "
              f"{row['io_share']:.1%} |")
    speedup = rows[1]["speedup"]
    print(f"two processes: {speedup:.2f}x one (goal >= {GOAL}x: "
          f"{'met' if speedup >= GOAL else 'missed'})")
    if args.json:
        for row in rows:
            row.pop("checksums")
        args.json.write_text(json.dumps({"settings": vars(args) | {"json": str(args.json)},
                                         "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
