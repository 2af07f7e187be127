"""EventBatch and the collate helpers, inside a DataLoader with worker processes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Dataset, Subset

from evdown_torch import CubicEstimation, EventCount, EventFunnelling, Events
from evdown_torch.collate import DownscaleCollate, EventBatch, EventsCollate, to_batch
from tests.helpers import random_stream

SENSOR = (9, 6, 2)


class _Recordings(Dataset):
    """Seeded random recordings of various lengths (one empty), with integer labels."""

    def __init__(self) -> None:
        rng = np.random.default_rng(7)
        sizes = [0, 1, 20, 53, 8, 31, 2, 40]
        self.samples = [random_stream(rng, n, SENSOR, t_max=500) for n in sizes]

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: int):
        return self.samples[i], i % 3


def _loader(dataset: Dataset, batch_size: int, collate_fn) -> DataLoader:
    """``dataset`` in batches of ``batch_size``, collated by ``collate_fn`` in two workers."""
    return DataLoader(dataset, batch_size=batch_size, num_workers=2, collate_fn=collate_fn)


def test_downscale_collate_in_dataloader_with_workers():
    dataset = _Recordings()
    down = EventCount(SENSOR, factor=2, threshold=0.5)
    seen = 0
    for outputs, targets in _loader(dataset, 3, DownscaleCollate(down)):
        assert isinstance(targets, torch.Tensor)
        for out, target in zip(outputs, targets.tolist(), strict=True):
            recording, want_target = dataset[seen]
            assert out.tolist() == down(recording).tolist()
            assert target == want_target
            seen += 1
    assert seen == len(dataset)


def test_downscale_collate_with_per_sample_and_collate():
    """Composes with Tonic: ToFrame on each output, PadTensors on the frames."""
    tonic = pytest.importorskip("tonic")
    dataset = _Recordings()
    down = EventFunnelling(SENSOR, factor=3)
    to_frame = tonic.transforms.ToFrame(sensor_size=down.output_sensor_size, n_event_bins=2)
    collate = DownscaleCollate(down, per_sample=to_frame,
                               collate=tonic.collation.PadTensors(batch_first=True))
    # Tonic's ToFrame gives empty input another shape, so the empty recording stays out.
    subset = Subset(dataset, range(1, 5))
    frames, targets = next(iter(_loader(subset, 4, collate)))
    first = [to_frame(down(subset[i][0])) for i in range(4)]
    assert frames.shape[0] == 4 and targets.tolist() == [1, 2, 0, 1]
    for i, want in enumerate(first):
        assert torch.equal(frames[i, : len(want)], torch.as_tensor(want, dtype=frames.dtype))


def test_events_collate_then_batch_on_device(device):
    """Collate in the workers, move the EventBatch, downscale on its device."""
    dataset = _Recordings()
    down = CubicEstimation(SENSOR, factor=2, threshold=0.5)
    seen = 0
    for batch, targets in _loader(dataset, 5, EventsCollate(SENSOR)):
        assert isinstance(batch, EventBatch) and len(targets) == batch.num_recordings
        out = down.batch(batch.to(device))
        assert out.device == device
        for part in out.unbind():
            want, _ = to_batch([down(dataset[seen][0])])
            assert all(torch.equal(a.cpu(), b) for a, b in zip(part, want.events, strict=True))
            seen += 1
    assert seen == len(dataset)


def test_event_batch_checks_lengths():
    events = Events.from_columns([0, 1], [0, 0], [1, 2], [1, 0])
    with pytest.raises(ValueError, match="add up to the number of events"):
        EventBatch(events, (1, 2))
    with pytest.raises(ValueError, match="non-negative"):
        EventBatch(events, (3, -1))
    assert [e.t.tolist() for e in EventBatch(events, (0, 2, 0)).unbind()] == [[], [1, 2], []]


def test_bare_events_without_targets():
    dataset = _Recordings()
    recordings = [dataset[i][0] for i in range(3)]
    batch = EventsCollate()(recordings)
    assert isinstance(batch, EventBatch) and batch.lengths == (0, 1, 20)
    down = EventFunnelling(SENSOR, factor=2)
    outputs = DownscaleCollate(down)(recordings)
    assert [o.tolist() for o in outputs] == [down(r).tolist() for r in recordings]
