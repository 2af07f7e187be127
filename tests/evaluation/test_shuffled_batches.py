"""ShuffledBatches gives the DataLoader's batches, drawn the same way, so training is the same."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import DataLoader, TensorDataset

from evdown_torch.evaluation.classifier import ShuffledBatches
from evdown_torch.models import SpikingClassifier
from evdown_torch.models.training import train_classifier


@pytest.mark.parametrize(("n", "batch"), [(32, 16), (37, 8), (5, 16)])
def test_the_same_batches_as_a_shuffling_dataloader_pass_after_pass(n, batch):
    x = torch.arange(n * 6, dtype=torch.float32).reshape(n, 3, 2)
    y = torch.arange(n) % 4
    ours = ShuffledBatches(x, y, batch, torch.Generator().manual_seed(7))
    loader = DataLoader(TensorDataset(x, y), batch_size=batch, shuffle=True,
                        generator=torch.Generator().manual_seed(7))
    for _ in range(3):  # each pass draws a new order, the same on both sides
        got, expected = list(ours), list(loader)
        assert len(got) == len(expected) == -(-n // batch)
        for (a, b), (c, d) in zip(got, expected):
            assert torch.equal(a, c) and torch.equal(b, d) and b.dtype == d.dtype
    assert torch.equal(ours.generator.get_state(), loader.generator.get_state())
    seen = torch.cat([b for _, b in got])
    assert sorted(seen.tolist()) == sorted(y.tolist())  # every sample once a pass


def test_training_on_them_is_the_same_to_the_bit():
    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(20, 3, 2, 6, 6, generator=g), torch.arange(20) % 3

    def trained(batches):
        torch.manual_seed(1)
        net = SpikingClassifier(num_classes=3, channels=(4,), pool_size=1)
        losses = train_classifier(net, batches, epochs=3, learning_rate=0.01)
        return losses, [p.detach().clone() for p in net.parameters()]

    ours = trained(ShuffledBatches(x, y, 8, torch.Generator().manual_seed(3)))
    loader = trained(DataLoader(TensorDataset(x, y), batch_size=8, shuffle=True,
                                generator=torch.Generator().manual_seed(3)))
    assert ours[0] == loader[0]
    assert all(torch.equal(a, b) for a, b in zip(ours[1], loader[1]))
