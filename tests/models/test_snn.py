"""The models' through-time leaky neuron against snntorch's Leaky stepped one call per step."""

import pytest
import snntorch
import torch
from snntorch import surrogate

from evdown_torch.models._snn import leaky_through_time


def _stepped(neuron, current, mem):
    spikes, membranes = [], []
    for step in current:
        spike, mem = neuron(step, mem)
        spikes.append(spike)
        membranes.append(mem)
    return torch.stack(spikes), torch.stack(membranes)


@pytest.mark.parametrize(("beta", "threshold", "slope", "shape"), [
    (0.9, 1.0, 25.0, (24, 3, 4, 5, 5)),
    (0.5, 0.3, 5.0, (7, 2, 11)),
    (1.0, 2.0, 25.0, (1, 6)),
])
def test_outputs_and_gradients_equal_snntorch_bit_for_bit(beta, threshold, slope, shape):
    g = torch.Generator().manual_seed(1)
    neuron = snntorch.Leaky(beta=beta, threshold=threshold,
                            spike_grad=surrogate.fast_sigmoid(slope=slope))
    current = (torch.randn(shape, generator=g) * threshold).requires_grad_()
    # Some neurons start above threshold: their first step subtracts the reset.
    mem = (torch.rand(shape[1:], generator=g) * 2 * threshold).requires_grad_()
    weight = torch.randn(shape, generator=g)

    spikes, membranes = _stepped(neuron, current, mem)
    assert 0 < spikes.sum() < spikes.numel()  # the comparison must see both
    (spikes * weight).sum().backward()
    expected = current.grad.clone(), mem.grad.clone()
    current.grad = mem.grad = None

    fast_spikes, fast_membranes = leaky_through_time(neuron, current, mem, slope)
    assert torch.equal(fast_spikes, spikes)
    assert torch.equal(fast_membranes, membranes)
    (fast_spikes * weight).sum().backward()
    assert torch.equal(current.grad, expected[0])
    assert torch.equal(mem.grad, expected[1])


def test_gradients_through_membranes_match_snntorch():
    """A loss on the membranes as well (three terms reach each membrane: equal up to the
    order of the float32 sums)."""
    g = torch.Generator().manual_seed(2)
    neuron = snntorch.Leaky(beta=0.8, threshold=1.0, spike_grad=surrogate.fast_sigmoid(slope=25))
    current = torch.randn(9, 4, 3, generator=g).requires_grad_()
    mem = torch.zeros(4, 3)
    w1, w2 = torch.randn(9, 4, 3, generator=g), torch.randn(9, 4, 3, generator=g)
    spikes, membranes = _stepped(neuron, current, mem)
    ((spikes * w1).sum() + (membranes * w2).sum() + membranes[-1].sum()).backward()
    expected, current.grad = current.grad.clone(), None
    spikes, membranes = leaky_through_time(neuron, current, mem, 25.0)
    ((spikes * w1).sum() + (membranes * w2).sum() + membranes[-1].sum()).backward()
    torch.testing.assert_close(current.grad, expected, rtol=1e-6, atol=1e-6)


def test_a_learnable_beta_is_refused():
    neuron = snntorch.Leaky(beta=0.9, learn_beta=True)
    with pytest.raises(ValueError, match="fixed beta"):
        leaky_through_time(neuron, torch.zeros(2, 3), torch.zeros(3), 25.0)
