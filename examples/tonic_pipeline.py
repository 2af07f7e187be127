"""Downscale a Tonic dataset on the fly and train on its frames through a DataLoader.

``ToFrames`` chains a downscaler with framing (as a Tonic ``transform=``, and unlike Tonic's
``Compose`` it frames empty outputs too); a ``DataLoader`` with worker processes
batches the frames for a spiking classifier. ``SyntheticGestures`` stands in for
``tonic.datasets.DVSGesture`` (same constructor and interface), so this runs offline; swap the
one word for the real dataset.

    python examples/tonic_pipeline.py                 # 2 workers, 3 recordings per class
    python examples/tonic_pipeline.py --workers 0 --samples-per-class 1 --duration-ms 300
"""

import argparse

import torch
from torch.utils.data import DataLoader

from evdown_torch import EventCount
from evdown_torch.frames import ToFrames
from evdown_torch.models import SpikingClassifier
from evdown_torch.models.training import evaluate_classifier, train_classifier
from evdown_torch.synthetic import SyntheticGestures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples-per-class", type=int, default=3)
    parser.add_argument("--duration-ms", type=int, default=1000)
    parser.add_argument("--workers", type=int, default=2, help="DataLoader worker processes")
    parser.add_argument("--epochs", type=int, default=2)
    args = parser.parse_args()

    sensor = (64, 64, 2)                            # DVSGesture is (128, 128, 2)
    down = EventCount(sensor, factor=4, threshold=0.5)
    # ToFrames downscales, then frames with one shape and dtype for every recording, even one
    # that downscales to nothing, so the default collate stacks the batch (Tonic's Compose
    # would stop at an empty output). A frozen dataclass, it pickles into worker processes.
    transform = ToFrames(down.output_sensor_size, n_time_bins=8, transform=down)

    kwargs = dict(transform=transform, samples_per_class=args.samples_per_class,
                  duration_us=args.duration_ms * 1000, sensor_size=sensor)
    train = SyntheticGestures("data", train=True, **kwargs)
    test = SyntheticGestures("data", train=False, **kwargs)
    order = torch.Generator().manual_seed(0)
    train_loader = DataLoader(train, batch_size=8, shuffle=True, generator=order,
                              num_workers=args.workers)
    test_loader = DataLoader(test, batch_size=16, num_workers=args.workers)

    x, labels = next(iter(train_loader))
    print(f"batch of frames: {tuple(x.shape)} {x.dtype}, labels {labels.tolist()}")

    torch.manual_seed(0)
    model = SpikingClassifier(num_classes=len(train.classes))
    # The loader gives frames [B, T, 2, H, W]; the training loop puts time first.
    train_classifier(model, train_loader, epochs=args.epochs, log=print)
    print(f"test accuracy: {evaluate_classifier(model, test_loader):.3f} "
          f"({len(test)} recordings; chance is {1 / len(train.classes):.3f})")


if __name__ == "__main__":      # needed where workers start by spawning (macOS, Windows)
    main()
