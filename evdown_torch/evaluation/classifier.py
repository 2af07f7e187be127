"""The classifier side of a study: a cell's frames as classifier input, and one training.

:func:`train_job` trains a fresh :class:`~evdown_torch.models.SpikingClassifier` on one seed's
own draw of training recordings (:func:`draw_training_set`), with inputs normalised per cell
(:func:`count_scale`), and tests it; it runs in a worker process and caches its predictions.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import DataLoader, TensorDataset

from evdown_torch.evaluation.cache import Cache, code_fingerprint
from evdown_torch.evaluation.cells import TIME_SCALE, Cell, frames_key
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.data import POOLED, StudyData
from evdown_torch.models.classifier import SpikingClassifier, stem_stride_for
from evdown_torch.models.training import predict_classifier, train_classifier

__all__ = [
    "ShuffledBatches", "count_scale", "draw_training_set", "frames_of", "model_for", "train_job",
    "trained_with",
]


def frames_of(source: StudyData, cell: Cell, split: str, chunks: dict[str, list[list[int]]],
              config: EvaluationConfig, draw: int = 0) -> tuple[Tensor, Tensor]:
    """A cell's classifier input and labels of ``split`` (after :func:`downscale_job`).

    ``chunks`` maps each split whose frames were made to its chunks of recordings: ``"train"``
    and ``"test"``, or under cross-validation ``"pooled"`` (every fold's frames made once),
    from which ``split``'s rows are taken by :meth:`StudyData.positions`.

    Returns:
        ``[n, T, C, H, W]`` float16 input (``C`` = ``data.frame_channels``: the counts
        encoded by ``training.encoding``, then the mean times in ``[-1, 1]``) and ``[n]``
        labels.
    """
    stored = POOLED if POOLED in chunks else split
    parts = [Cache.load_tensors(source.cache.path(
        "frames", frames_key(source, cell, stored, c, config, draw), ".pt"))
        for c in chunks[stored]]
    frames = torch.cat([p["frames"] for p in parts])
    labels = torch.cat([p["labels"] for p in parts])
    rows = None if stored == split else torch.tensor(source.positions(split), dtype=torch.int64)
    if rows is not None:
        frames, labels = frames[rows], labels[rows]
    x = _encode(frames, config.training.encoding)
    if config.data.mean_time:
        times = torch.cat([p["times"] for p in parts])
        times = (times if rows is None else times[rows]).to(torch.float16) / TIME_SCALE
        x = torch.cat([x.to(torch.float16), times], dim=2)
    return x, labels


class ShuffledBatches:
    """``(x[rows], y[rows])`` in a fresh shuffled order on every pass, taken whole.

    The batches ``DataLoader(TensorDataset(x, y), batch_size, shuffle=True,
    generator=generator)`` gives, drawn from ``generator`` the same way (per pass: the
    loader's base seed, the permutation, and the permutation its sampler draws for the
    remainder when the pass ends), so training on either is the same to the bit; but each
    batch is one indexing of the whole tensors instead of a collation of one sample at a time,
    which cost about a tenth of a small classifier's training. ``tests/evaluation`` holds it
    to the DataLoader.

    Args:
        x: ``[N, ...]`` inputs.
        y: ``[N]`` labels.
        batch_size: samples per batch (the last batch may be smaller).
        generator: the shuffling's random source, advanced by every pass.
    """

    def __init__(self, x: Tensor, y: Tensor, batch_size: int, generator: torch.Generator
                 ) -> None:
        self.x, self.y, self.batch_size, self.generator = x, y, batch_size, generator

    def __iter__(self) -> Iterator[tuple[Tensor, Tensor]]:
        n = self.y.shape[0]
        torch.empty((), dtype=torch.int64).random_(generator=self.generator)  # the base seed
        order = torch.randperm(n, generator=self.generator)
        for lo in range(0, n, self.batch_size):
            rows = order[lo:lo + self.batch_size]
            yield self.x[rows], self.y[rows]
        torch.randperm(n, generator=self.generator)  # the sampler's draw for the remainder


def trained_with(config: EvaluationConfig, cell: Cell) -> EvaluationConfig:
    """``config`` as ``cell`` trains under it: its :attr:`~.cells.Cell.classifier` in place.

    Example:
        >>> from evdown_torch.evaluation.config import parse_config
        >>> config = parse_config({"model": {"channels": [8]}, "training": {"epochs": 3}})
        >>> wide = trained_with(config, Cell("event_count", (4, 4), 1.0,
        ...                                  classifier=(("channels", (16, 32)),)))
        >>> wide.model.channels, wide.training.epochs, config.model.channels
        ((16, 32), 3, (8,))
    """
    if not cell.classifier:
        return config
    given = dict(cell.classifier)
    return replace(config, model=replace(config.model, channels=given.get(
        "channels", config.model.channels)), training=replace(config.training, epochs=given.get(
            "epochs", config.training.epochs)))


def model_for(config: EvaluationConfig, size: tuple[int, int], num_classes: int
              ) -> SpikingClassifier:
    """The classifier of a cell whose frames are ``size = (W, H)``."""
    m = config.model
    return SpikingClassifier(
        num_classes, in_channels=config.data.frame_channels, channels=m.channels,
        pool_size=m.pool_size, beta=m.beta, threshold=m.threshold,
        stem_stride=stem_stride_for(size, m.grid) if m.grid else 1,
        stem_channels=m.stem_channels,
    )


def _encode(counts: Tensor, encoding: str) -> Tensor:
    """Classifier input from event counts (float16 for ``log``, ``binary``; else float32)."""
    counts = counts.to(torch.float32)
    if encoding == "log":
        return torch.log1p(counts).to(torch.float16)
    if encoding == "binary":
        return (counts > 0).to(torch.float16)
    return counts


def count_scale(x: Tensor) -> float:
    """The root mean square of the count channels (0 and 1) of ``[n, T, C, H, W]`` input.

    Dividing a cell's input by the scale of its training frames gives every cell input of
    the same energy, whatever its event rate: a dense cell (every event of Downsample) is not
    fed currents many times those of a sparse one (the same events thinned), which would
    saturate the first spiking layer and make a superset of events score below its subset.
    An input without events has scale 1.

    Example:
        >>> import torch
        >>> x = torch.zeros(2, 3, 4, 5, 5)
        >>> x[:, :, :2] = 2.0
        >>> count_scale(x), count_scale(torch.zeros(1, 1, 2, 1, 1))
        (2.0, 1.0)
    """
    counts = x[:, :, :2].to(torch.float64)
    rms = float(counts.square().mean().sqrt()) if counts.numel() else 0.0
    return rms if rms > 0 else 1.0


def draw_training_set(labels: Tensor, per_seed: int, seed: int,
                      exclude: int = 0) -> Tensor:
    """The training recordings of one seed: a class-stratified draw without replacement.

    Each seed trains on its own draw from the training pool (its rows ``exclude:`` of
    ``labels``; the first ``exclude`` are the validation recordings), so that seeds vary
    the training set as a replication would. Each class gives ``per_seed // classes``
    recordings, the remainder going one each to the classes in order; a class with fewer
    gives all it has.

    Args:
        labels: ``[n]`` int64 labels of the pool.
        per_seed: recordings wanted (0: the whole pool past ``exclude``).
        seed: the draw's seed.
        exclude: leading rows never drawn.

    Returns:
        Sorted ``[m]`` int64 row indices into ``labels``.

    Example:
        >>> import torch
        >>> labels = torch.arange(12) % 3
        >>> rows = draw_training_set(labels, 6, seed=0)
        >>> len(rows), torch.bincount(labels[rows]).tolist()
        (6, [2, 2, 2])
        >>> bool((draw_training_set(labels, 6, seed=1, exclude=3) >= 3).all())
        True
    """
    rows = torch.arange(exclude, len(labels))
    if per_seed == 0 or per_seed >= len(rows):
        return rows
    pool = labels[exclude:]
    classes = torch.unique(pool)
    g = torch.Generator().manual_seed(int(seed))
    base, extra = divmod(per_seed, len(classes))
    chosen = []
    for k, c in enumerate(classes.tolist()):
        members = rows[pool == c]
        take = min(len(members), base + (k < extra))
        chosen.append(members[torch.randperm(len(members), generator=g)[:take]])
    return torch.sort(torch.cat(chosen)).values


def train_job(source: StudyData, cell: Cell, chunks: dict[str, list[list[int]]],
              config: EvaluationConfig, seed: int, device: str, learning_rate: float,
              validation: bool = False) -> dict[str, Any]:
    """Train a fresh classifier on ``cell``'s frames under ``seed``; test it.

    Seed ``s`` fixes the initial weights, the order of the batches, the draw of training
    recordings from the pool (:func:`draw_training_set`) and, for the thinning control, the
    thinning draw. With ``validation`` the classifier trains on a draw from the pool less
    its first ``data.validation_samples`` recordings and is tested on those (to choose the
    learning rate); otherwise it trains on a draw from the whole pool and is tested on the
    test split. With ``training.normalise`` the count channels are divided by their
    :func:`count_scale` over the seed's training frames (train and test alike).

    Returns:
        ``{"correct": [bool per test recording], "predicted": [int per test recording],
        "labels": [int per test recording], "seconds": training time}`` (cached).
    """
    config = trained_with(config, cell)
    training = config.training
    draw = seed if cell.random else 0
    splits = ("train",) if validation else ("train", "test")
    frames_keys: dict[str, Any] = {
        s: [frames_key(source, cell, s, c, config, draw) for c in chunks[s]]
        for s in (chunks if POOLED in chunks else splits)}
    if POOLED in chunks:
        frames_keys["fold"] = source.fold
    held_out = config.data.validation_samples if validation else 0
    key = {"frames": frames_keys, "model": config.model.__dict__, "epochs": training.epochs,
           "batch_size": training.batch_size, "learning_rate": learning_rate,
           "encoding": training.encoding, "normalise": training.normalise,
           "per_seed": config.data.train_per_seed, "validation": held_out, "seed": seed,
           "device": torch.device(device).type,
           "code": code_fingerprint("models", "evaluation/classifier.py")}
    cache = source.cache
    path = cache.path("predictions", key, ".json")
    if path.is_file():
        return Cache.load_json(path)
    pool_x, pool_y = frames_of(source, cell, "train", chunks, config, draw)
    rows = draw_training_set(pool_y, config.data.train_per_seed, seed, exclude=held_out)
    train_x, train_y = pool_x[rows], pool_y[rows]
    if validation:
        test_x, test_y = pool_x[:held_out], pool_y[:held_out]
    else:
        test_x, test_y = frames_of(source, cell, "test", chunks, config, draw)
    del pool_x
    if training.normalise:
        scale = count_scale(train_x)
        for x in (train_x, test_x):
            x[:, :, :2] /= scale
    size = (train_x.shape[-1], train_x.shape[-2])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = model_for(config, size, source.num_classes)
    model.to(device)
    order = torch.Generator().manual_seed(seed)
    start = time.perf_counter()
    train_classifier(model, ShuffledBatches(train_x, train_y, training.batch_size, order),
                     epochs=training.epochs, learning_rate=learning_rate)
    seconds = time.perf_counter() - start
    predicted, labels = predict_classifier(
        model, DataLoader(TensorDataset(test_x, test_y), batch_size=training.batch_size))
    result = {"correct": (predicted == labels).tolist(), "predicted": predicted.tolist(),
              "labels": labels.tolist(), "seconds": seconds}
    cache.save_json(path, result)
    return result
