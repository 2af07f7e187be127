"""Downscale a folder of recordings once into a cache, then train-ready reads from it.

A dataset folder holds one ``.npy`` Tonic structured array per recording under
``ROOT/CLASS/`` (the label is the class folder's index in sorted order). This script writes
such a folder from synthetic gestures (so it runs offline), downscales it with worker
processes into a cache of shards (``evdown preprocess`` does the same from the shell), and
reads the cache back as a Tonic-style dataset in a ``DataLoader``.

    python examples/preprocess_folder.py                       # in a temporary folder
    python examples/preprocess_folder.py --out cache-demo --workers 1 --recordings 2
"""

import argparse
import tempfile
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from evdown_torch.data import PreprocessedDataset, open_source, preprocess
from evdown_torch.frames import to_frames
from evdown_torch.synthetic import SyntheticGestures

SENSOR = (64, 64, 2)


def write_folder(root: Path, recordings_per_class: int, duration_ms: int) -> None:
    """Write ``root/CLASS/NNN.npy`` for three gesture classes (stands in for your recordings)."""
    gestures = SyntheticGestures(train=True, samples_per_class=recordings_per_class,
                                 duration_us=duration_ms * 1000, sensor_size=SENSOR)
    classes = 3
    for i in range(len(gestures)):
        if i % len(gestures.classes) < classes:   # sample i has label i % 11
            events, label = gestures[i]
            folder = root / gestures.classes[label]
            folder.mkdir(parents=True, exist_ok=True)
            np.save(folder / f"{i:03d}.npy", events)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="working folder (default: a temporary one)")
    parser.add_argument("--recordings", type=int, default=4, help="recordings per class")
    parser.add_argument("--duration-ms", type=int, default=500)
    parser.add_argument("--workers", type=int, default=2, help="processes, this one included")
    args = parser.parse_args()
    torch.set_num_threads(1)        # the generator's many small operations: one thread is best

    with tempfile.TemporaryDirectory() as scratch:
        work = args.out if args.out is not None else Path(scratch)
        write_folder(work / "recordings", args.recordings, args.duration_ms)

        source = open_source(f"folder:{work / 'recordings'}", sensor_size=SENSOR)
        result = preprocess(source, work / "cache", "event_count", 4, {"threshold": 0.5},
                            shard_size=4, workers=args.workers, progress=False)
        print(f"{len(source)} recordings -> {result.shards} shards in {result.out} "
              f"({result.seconds:.1f} s)")

        frames = partial(to_frames, sensor_size=(16, 16, 2), n_time_bins=5)
        cache = PreprocessedDataset(work / "cache", transform=frames)   # checksums verified
        print(f"cache: {len(cache)} recordings on a {cache.sensor_size} sensor, "
              f"method {cache.manifest['method']}")
        loader = DataLoader(cache, batch_size=4, shuffle=False)
        x, labels = next(iter(loader))
        print(f"first batch: frames {tuple(x.shape)}, labels {labels.tolist()}")
        # A rerun of the same job keeps every shard whose checksums verify.
        again = preprocess(source, work / "cache", "event_count", 4, {"threshold": 0.5},
                           shard_size=4, workers=1, progress=False)
        print(f"rerun: {len(again.kept)} shards kept, {len(again.written)} written")


if __name__ == "__main__":      # preprocess() spawns its worker processes
    main()
