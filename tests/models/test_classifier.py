"""SpikingClassifier: shapes for any input size, explicit state, buffers, learning."""

from __future__ import annotations

import re

import pytest
import torch

from evdown_torch.models import SpikingClassifier
from evdown_torch.models.classifier import class_scores
from evdown_torch.models.training import evaluate_classifier, train_classifier


@pytest.mark.parametrize("size", [(1, 1), (2, 3), (7, 5), (32, 32), (64, 48)])
def test_any_input_size(size):
    net = SpikingClassifier(num_classes=11, channels=(4, 8), pool_size=3)
    x = torch.rand(3, 2, 2, *size, generator=torch.Generator().manual_seed(0))
    spikes, membrane, state = net(x)
    assert spikes.shape == membrane.shape == (3, 2, 11)
    assert set(spikes.unique().tolist()) <= {0.0, 1.0}
    assert state.out.shape == (2, 11) and len(state.conv) == 2
    assert state.conv[0].shape[-2:] == (-(-size[0] // 2), -(-size[1] // 2))


def test_state_carries_over_between_calls():
    torch.manual_seed(0)
    net = SpikingClassifier(num_classes=4, channels=(6,), pool_size=2)
    x = 3 * torch.rand(6, 2, 2, 8, 8, generator=torch.Generator().manual_seed(1))
    whole_spikes, whole_mem, whole_state = net(x)
    first_spikes, first_mem, state = net(x[:4])
    rest_spikes, rest_mem, last_state = net(x[4:], state)
    torch.testing.assert_close(torch.cat([first_spikes, rest_spikes]), whole_spikes)
    torch.testing.assert_close(torch.cat([first_mem, rest_mem]), whole_mem)
    torch.testing.assert_close(last_state.out, whole_state.out)


def test_constants_are_buffers_and_state_dict_round_trips():
    net = SpikingClassifier(num_classes=3, channels=(4,), pool_size=2, beta=0.8, threshold=0.5)
    keys = set(net.state_dict())
    assert {"out_neuron.beta", "out_neuron.threshold", "conv_neurons.0.beta"} <= keys
    torch.manual_seed(1)
    other = SpikingClassifier(num_classes=3, channels=(4,), pool_size=2, beta=0.8, threshold=0.5)
    other.load_state_dict(net.state_dict())
    x = torch.rand(4, 1, 2, 5, 5, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(other(x)[1], net(x)[1])
    text = repr(net)
    assert "num_classes=3" in text and "beta=0.8" in text and "threshold=0.5" in text


def test_gradients_are_finite():
    net = SpikingClassifier(num_classes=5, channels=(4, 4), pool_size=2)
    x = 2 * torch.rand(5, 3, 2, 9, 9, generator=torch.Generator().manual_seed(3))
    spikes, membrane, _ = net(x)
    (spikes.sum() + membrane.sum()).backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)


def test_class_scores_break_ties_by_membrane():
    spikes = torch.tensor([[[1.0, 1.0, 0.0]], [[0.0, 0.0, 1.0]]])  # counts 1, 1, 1
    membrane = torch.tensor([[[0.1, 0.9, 0.0]], [[0.0, 0.3, -0.5]]])
    assert class_scores(spikes, membrane).argmax(1).tolist() == [1]
    counts = torch.tensor([[[0.0, 1.0, 0.0]], [[0.0, 1.0, 0.0]]])
    big_membrane = torch.tensor([[[50.0, 0.0, 0.0]], [[50.0, 0.0, 0.0]]])
    assert class_scores(counts, big_membrane).argmax(1).tolist() == [1]


@pytest.mark.slow
def test_learns_a_separable_task():
    """Class k: events in column block k; a few epochs reach perfect accuracy."""
    g = torch.Generator().manual_seed(4)
    labels = torch.arange(24) % 3
    frames = 0.1 * torch.rand(24, 4, 2, 6, 9, generator=g)
    for i, k in enumerate(labels.tolist()):
        frames[i, :, :, :, 3 * k : 3 * k + 3] += 1.0
    batches = [(frames[i : i + 8], labels[i : i + 8]) for i in range(0, 24, 8)]
    torch.manual_seed(0)
    net = SpikingClassifier(num_classes=3, channels=(8,), pool_size=3)
    lines = []
    losses = train_classifier(net, batches, epochs=6, learning_rate=2e-2, log=lines.append)
    assert losses[-1] < losses[0]
    assert len(lines) == 6  # one line per epoch: its loss and the seconds since the start
    for epoch, (line, loss) in enumerate(zip(lines, losses, strict=True)):
        match = re.fullmatch(rf"epoch {epoch + 1}/6: loss {loss:.4f}, (\d+\.\d) s", line)
        assert match is not None, line
    seconds = [float(re.search(r"([\d.]+) s$", line).group(1)) for line in lines]
    assert seconds == sorted(seconds)
    assert evaluate_classifier(net, batches) == 1.0


def test_bad_settings_and_input():
    with pytest.raises(ValueError, match="num_classes must be a positive integer"):
        SpikingClassifier(num_classes=0)
    with pytest.raises(TypeError, match="channels must be a sequence"):
        SpikingClassifier(channels=16)
    with pytest.raises(ValueError, match="beta must lie in"):
        SpikingClassifier(beta=1.5)
    with pytest.raises(ValueError, match=r"input must have shape \[T, B, 2, H, W\]"):
        SpikingClassifier()(torch.zeros(2, 1, 3, 4, 4))
    with pytest.raises(ValueError, match="no samples"):
        evaluate_classifier(SpikingClassifier(), [])


def test_device(device):
    net = SpikingClassifier(num_classes=2, channels=(2,), pool_size=1).to(device)
    spikes, _, state = net(torch.rand(2, 1, 2, 4, 4, device=device))
    assert spikes.device.type == device.type and state.out.device.type == device.type


def _blocks_of_ones(model, size, channels=2):
    """An input that needs a gradient and the last block's output on it, every weight 1 and
    every bias 0 (convolutions and pooling only, so nothing cancels)."""
    x = torch.zeros(1, channels, size, size, requires_grad=True)
    with torch.no_grad():
        for p in model.parameters():
            p.fill_(1.0) if p.ndim > 1 else p.zero_()
    current = model._stem(x)
    for conv in model.convs:
        current = model.pool(conv(current))
    return x, current


def _receptive_mask(model, size):
    """Which input pixels reach the centre unit of the last block."""
    x, current = _blocks_of_ones(model, size)
    h, w = current.shape[-2:]
    current[0, 0, h // 2, w // 2].backward()
    return x.grad[0].abs().sum(0) > 0


@pytest.mark.parametrize("size", [128, 64, 16])
def test_receptive_field_covers_the_input(size):
    from evdown_torch.models.classifier import stem_stride_for

    stride = stem_stride_for((size, size), 16)
    model = SpikingClassifier(11, channels=(16, 32, 32, 32), stem_stride=stride)
    assert bool(_receptive_mask(model, size).all())
    # without the stem, four blocks see only a corner of 128x128
    if size == 128:
        plain = SpikingClassifier(11, channels=(16, 32, 32, 32))
        assert not bool(_receptive_mask(plain, size).all())


def test_stem_shapes_and_macs():
    model = SpikingClassifier(3, channels=(4,), pool_size=2, stem_stride=4, stem_channels=2)
    spikes, _, state = model(torch.rand(2, 1, 2, 10, 9))
    assert spikes.shape == (2, 1, 3) and state.conv[0].shape == (1, 4, 2, 2)
    # stem: 3x3 outputs * 2 ch * 2 in * 16; block: 3x3 * 4 * 2 * 9; fc: 4*2*2 -> 3
    assert model.macs_per_step(10, 9) == 9 * 2 * 2 * 16 + 9 * 4 * 2 * 9 + 16 * 3


@pytest.mark.parametrize(("name", "side"), [("quick", 32), ("quick", 16), ("full", 128)])
def test_the_study_classifiers_see_the_whole_input(name, side):
    """Every pixel of a study's input reaches the linear layer (quick at x4 and x8 without a
    stem; full at full resolution through its stem)."""
    from pathlib import Path

    from evdown_torch.evaluation.classifier import model_for
    from evdown_torch.evaluation.config import load_config

    config = load_config(Path(__file__).resolve().parents[2] / "configs" / f"{name}.toml")
    model = model_for(config, (side, side), 11)
    assert (model.stem is None) == (side <= config.model.grid)
    x, current = _blocks_of_ones(model, side, config.data.frame_channels)
    model.fc(model.squeeze(current).flatten(1)).sum().backward()
    assert bool((x.grad.abs().sum(1) > 0).all())


def test_all_steps_at_once_equal_one_step_at_a_time():
    """The layer-by-layer forward (each convolution over all steps at once) is the network
    stepped through time: one call on T steps equals T calls of one step carrying the state."""
    torch.manual_seed(0)
    net = SpikingClassifier(num_classes=4, in_channels=4, channels=(6, 8), pool_size=2,
                            stem_stride=2, stem_channels=3, threshold=0.3)
    x = torch.rand(7, 3, 4, 9, 10) * 2
    spikes, membrane, state = net(x)
    assert spikes.sum() > 0  # the comparison must see spikes
    stepped_state, stepped_spikes, stepped_membrane = None, [], []
    for t in range(x.shape[0]):
        s, m, stepped_state = net(x[t:t + 1], stepped_state)
        stepped_spikes.append(s)
        stepped_membrane.append(m)
    torch.testing.assert_close(torch.cat(stepped_spikes), spikes, rtol=0, atol=0)
    torch.testing.assert_close(torch.cat(stepped_membrane), membrane, rtol=1e-6, atol=1e-6)
    for a, b in zip(state.conv, stepped_state.conv):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)


def test_the_classifier_saves_and_loads_whole():
    import io

    torch.manual_seed(0)
    net = SpikingClassifier(num_classes=3, channels=(4,), pool_size=2)
    x = torch.rand(5, 2, 2, 8, 8)
    buffer = io.BytesIO()
    torch.save(net, buffer)  # snntorch's fast_sigmoid(slope) was a closure pickle refused
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=False)
    assert torch.equal(loaded(x)[0], net(x)[0])
