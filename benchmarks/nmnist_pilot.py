"""The pilot that fixed the classifier settings of ``configs/nmnist.toml``, on held-out data.

It trains the study's classifier (``[model]`` of the config, counts ``log``-encoded and
divided by their RMS as in the study) on Downsample's frames of N-MNIST recordings that the
study never reads: recordings of the folder's Train outside the config's ``train_samples``
(drawn with its ``data.seed``), 320 to train and 80 to test. One seed per setting; the
accuracies are on 80 recordings, so a difference of less than about 0.1 means little.

    python benchmarks/nmnist_pilot.py                       # the settings the config took
    python benchmarks/nmnist_pilot.py --bins 6 12 --epochs 15 30 --rates 0.003 0.005 0.01

Prints one line per (factor, bins, epochs, rate): the test accuracy and the training time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader, TensorDataset

from evdown_torch import Downsample
from evdown_torch.data.sources import NMNISTSource
from evdown_torch.evaluation.classifier import count_scale
from evdown_torch.evaluation.config import EvaluationConfig, load_config
from evdown_torch.evaluation.data import outside_study
from evdown_torch.events import to_events
from evdown_torch.frames import to_frames
from evdown_torch.io import NMNIST_SENSOR
from evdown_torch.models.classifier import SpikingClassifier, stem_stride_for
from evdown_torch.models.training import predict_classifier, train_classifier

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "nmnist.toml"


def held_out(config: EvaluationConfig, count: int, seed: int) -> list[int]:
    """``count`` indices of the folder's Train that the study does not use."""
    rest = outside_study(config.data)
    order = torch.randperm(len(rest), generator=torch.Generator().manual_seed(seed))
    return [rest[i] for i in order[:count].tolist()]


def frames(source: NMNISTSource, indices: list[int], factor: int, bins: int
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """``[n, bins, 2, H, W]`` log counts of Downsample at ``factor``, and the labels."""
    transform = Downsample(NMNIST_SENSOR, factor) if factor > 1 else None
    out_size = transform.output_sensor_size if transform is not None else NMNIST_SENSOR
    xs, ys = [], []
    for i in indices:
        raw, label = source.load(i)
        events = to_events(raw, NMNIST_SENSOR)[0]
        if transform is not None:
            events = transform.kernel(events)
        t0, t1 = int(raw["t"].min()), int(raw["t"].max())
        xs.append(to_frames(events, out_size, bins, t_start=t0, t_end=t1)[:, :2])
        ys.append(int(label))
    return torch.log1p(torch.stack(xs).float()), torch.tensor(ys)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default=str(CONFIG))
    parser.add_argument("--factors", type=int, nargs="+", default=[4, 2])
    parser.add_argument("--bins", type=int, nargs="+", default=[12])
    parser.add_argument("--epochs", type=int, nargs="+", default=[30])
    parser.add_argument("--rates", type=float, nargs="+", default=[0.005])
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--seed", type=int, default=7, help="which held-out recordings")
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = load_config(args.config)
    source = NMNISTSource(config.data.root, split="train")
    indices = held_out(config, 400, args.seed)
    m = config.model
    for factor in args.factors:
        for bins in args.bins:
            x, y = frames(source, indices, factor, bins)
            train, test = slice(0, 320), slice(320, 400)
            x = x / count_scale(x[train])
            for epochs in args.epochs:
                for rate in args.rates:
                    torch.manual_seed(0)
                    size = (x.shape[-1], x.shape[-2])
                    model = SpikingClassifier(
                        10, in_channels=2, channels=m.channels, pool_size=m.pool_size,
                        stem_stride=stem_stride_for(size, m.grid) if m.grid else 1,
                        stem_channels=m.stem_channels)
                    start = time.perf_counter()
                    train_classifier(model, DataLoader(
                        TensorDataset(x[train], y[train]), batch_size=args.batch, shuffle=True,
                        generator=torch.Generator().manual_seed(0)),
                        epochs=epochs, learning_rate=rate)
                    seconds = time.perf_counter() - start
                    predicted, labels = predict_classifier(model, DataLoader(
                        TensorDataset(x[test], y[test]), batch_size=16))
                    accuracy = float((predicted == labels).double().mean())
                    print(f"x{factor} bins={bins} epochs={epochs} rate={rate:g} "
                          f"batch={args.batch}: accuracy {accuracy:.3f} "
                          f"({seconds:.1f} s training)", flush=True)


if __name__ == "__main__":
    main()
