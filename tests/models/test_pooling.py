"""SpikingPooling against hand-computed traces, its limits, gradients, state and compile."""

from __future__ import annotations

import copy
import gc
import math
import re

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from evdown_torch.models import SpikingPooling, SpikingPoolingLayer, reset_states
from evdown_torch.models.pooling import decay_factor


def block_input(counts: list[int], *, factor: int = 2, channel: int = 1) -> torch.Tensor:
    """``(T, 1, 2, f, f)`` input: ``counts[k]`` events of ``channel`` in the block at step ``k``,
    spread over distinct pixels in turn (so it is a valid spike tensor for counts <= f * f)."""
    x = torch.zeros(len(counts), 1, 2, factor, factor)
    pixel = 0
    for k, c in enumerate(counts):
        for _ in range(c):
            x[k, 0, channel].view(-1)[pixel % (factor * factor)] += 1
            pixel += 1
    return x


@pytest.mark.parametrize("factor", [2, 4])
def test_integrate_and_fire_limit_fires_once_per_n_events(factor):
    # beta = 1, subtract reset, weight 1/n, threshold 1, one ON event per step. After k + 1
    # events the membrane is (k + 1)/n minus one per earlier spike; snntorch fires when it
    # *exceeds* 1, so the first spike needs n + 1 events (step n), and each later one n more:
    # spikes at steps n, 2n, 3n, ... (1/n is a power of two here, so the sums are exact).
    n = factor * factor
    steps = 5 * n + 3
    pool = SpikingPooling(factor, tau=math.inf, weight=1 / n, threshold=1.0)
    spikes, mem = pool(block_input([1] * steps, factor=factor))
    fired = spikes[:, 0, 1, 0, 0].nonzero().squeeze(1).tolist()
    assert fired == [n, 2 * n, 3 * n, 4 * n, 5 * n]
    assert spikes[:, 0, 0].sum() == 0  # the OFF neuron got nothing
    # Membrane after the last step: (steps) / n - (spikes before the last step).
    assert mem[0, 1, 0, 0].item() == steps / n - 5


def test_hand_computed_leaky_trace():
    # beta 0.5, weight 0.5, threshold 1; ON events per step 2, 1, 0, 3, 0, 0.
    counts = [2, 1, 0, 3, 0, 0]
    expected = {
        # U_k = 0.5 U_{k-1} + 0.5 c_k - R_k (R_k = [U_{k-1} > 1]); fires when U_k > 1
        "subtract": ([1.0, 1.0, 0.5, 1.75, -0.125, -0.0625], [0, 0, 0, 1, 0, 0]),
        # reset to zero: U_4 = 0.5 * 0 + 0
        "zero": ([1.0, 1.0, 0.5, 1.75, 0.0, 0.0], [0, 0, 0, 1, 0, 0]),
        "none": ([1.0, 1.0, 0.5, 1.75, 0.875, 0.4375], [0, 0, 0, 1, 0, 0]),
    }
    x = block_input(counts)
    for reset, (trace, fired) in expected.items():
        pool = SpikingPooling(2, beta=0.5, weight=0.5, threshold=1.0, reset_mechanism=reset)
        state, mems, spikes = None, [], []
        for k in range(len(counts)):
            spike, state = pool.step(x[k], state)
            mems.append(state[0, 1, 0, 0].item())
            spikes.append(int(spike[0, 1, 0, 0].item()))
        assert mems == trace, reset
        assert spikes == fired, reset


def test_membrane_above_threshold_keeps_firing_without_input():
    # 5 events at weight 0.5: U_0 = 2.5. Without input and beta = 1: subtract fires while
    # U - 1 > 1 (2.5 -> 1.5 -> 0.5), zero resets after one spike, none fires every step.
    x = block_input([4, 0, 0, 0, 0])
    x[0, 0, 1, 0, 0] += 1
    expected = {"subtract": [1, 1, 0, 0, 0], "zero": [1, 0, 0, 0, 0], "none": [1, 1, 1, 1, 1]}
    for reset, fired in expected.items():
        pool = SpikingPooling(2, beta=1.0, weight=0.5, reset_mechanism=reset)
        spikes, _ = pool(x)
        assert spikes[:, 0, 1, 0, 0].tolist() == fired, reset


def test_mutual_inhibition_cancels_balanced_input(rng):
    # The same number of ON and OFF events in every block and step: with w_inh = w the current
    # is exactly zero, so nothing fires; without inhibition both neurons fire.
    counts = torch.from_numpy(rng.integers(0, 3, size=(30, 2, 3, 3))).float()
    x = torch.zeros(30, 2, 2, 6, 6)
    x[:, :, 0, ::2, ::2] = counts  # OFF at even pixels
    x[:, :, 1, 1::2, 1::2] = counts  # ON at odd pixels of the same 2x2 blocks
    inhibited = SpikingPooling(2, tau=5.0, weight=0.7, mutual_inhibition=0.7)
    spikes, mem = inhibited(x)
    assert spikes.sum() == 0 and mem.abs().max() == 0
    spikes, _ = SpikingPooling(2, tau=5.0, weight=0.7)(x)
    assert spikes[:, :, 0].sum() > 0 and spikes[:, :, 1].sum() > 0


def test_current_is_the_pooling_convolution(rng):
    pool = SpikingPooling((3, 2), beta=0.9, weight=0.37, mutual_inhibition=0.11)
    x = torch.from_numpy(rng.integers(0, 3, size=(4, 2, 2, 7, 8))).float()
    padded = F.pad(x.flatten(0, 1), (0, 1, 0, 1))  # 8 -> 9 columns, 7 -> 8 rows
    conv = F.conv2d(padded, pool.conv_weight, stride=(2, 3)).unflatten(0, (4, 2))
    current = pool.current(x)
    assert current.shape == (4, 2, 2, 4, 3)
    torch.testing.assert_close(current, conv)
    assert pool.conv_weight[0, 0, 1, 2] == pytest.approx(0.37)
    assert pool.conv_weight[1, 0, 0, 0] == pytest.approx(-0.11)


def test_output_shape_with_padded_edge_blocks():
    pool = SpikingPooling((4, 3), beta=1.0, weight=2.0)
    x = torch.zeros(2, 3, 2, 7, 10)
    x[0, 1, 0, 6, 9] = 1  # bottom-right pixel: the padded block (2, 2)
    spikes, mem = pool(x)
    assert spikes.shape == (2, 3, 2, 3, 3) and mem.shape == (3, 2, 3, 3)
    assert spikes.nonzero().tolist() == [[0, 1, 0, 2, 2]]


def test_tau_limits(rng):
    x = torch.from_numpy(rng.integers(0, 2, size=(40, 2, 2, 4, 4))).float()
    # tau -> 0: beta = 0, no memory; with reset to zero a neuron fires iff its current does.
    memoryless = SpikingPooling(2, tau=1e-6, weight=0.3, reset_mechanism="zero")
    assert memoryless.beta == 0.0
    spikes, _ = memoryless(x)
    assert torch.equal(spikes, (memoryless.current(x) > 1.0).float())
    # tau -> inf: beta = 1, the membrane without reset is the running sum of the current.
    integrator = SpikingPooling(2, tau=1e30, weight=0.25, reset_mechanism="none")
    assert integrator.beta == 1.0
    spikes, mem = integrator(x)
    total = torch.cumsum(integrator.current(x), 0)
    assert torch.equal(mem, total[-1])
    assert torch.equal(spikes, (total > 1.0).float())
    # and it is the same neuron as tau = math.inf
    inf_spikes, _ = SpikingPooling(2, tau=math.inf, weight=0.25, reset_mechanism="none")(x)
    assert torch.equal(inf_spikes, spikes)
    assert decay_factor(1.0, 1e-6) == 0.0 and decay_factor(1.0, math.inf) == 1.0
    assert 0 < decay_factor(1.0, 1.0) == pytest.approx(math.exp(-1))


def test_dt_and_tau_set_beta():
    assert SpikingPooling(2, tau=20.0, dt=5.0).beta == pytest.approx(math.exp(-0.25))
    assert SpikingPooling(2, beta=0.75).beta == 0.75
    assert SpikingPooling(2).beta == pytest.approx(math.exp(-0.1))  # default tau: 10 steps


def test_state_is_explicit_and_chunks_compose(rng):
    pool = SpikingPooling(2, tau=3.0, weight=0.6, mutual_inhibition=0.2)
    x = torch.from_numpy(rng.integers(0, 2, size=(20, 3, 2, 4, 6))).float()
    whole, mem = pool(x)
    first, state = pool(x[:7])
    second, state = pool(x[7:], state)
    assert torch.equal(torch.cat([first, second]), whole) and torch.equal(state, mem)
    again, _ = pool(x)  # no hidden state carried over
    assert torch.equal(again, whole)
    spike, _ = pool.step(x[0])
    assert torch.equal(spike, whole[0])


def test_backward_gives_finite_gradients(rng):
    pool = SpikingPooling(2, tau=4.0, weight=0.4, mutual_inhibition=0.1, learnable=True)
    assert {name for name, _ in pool.named_parameters()} == {"weight", "mutual_inhibition"}
    x = torch.from_numpy(rng.integers(0, 2, size=(15, 2, 2, 6, 6))).float().requires_grad_()
    spikes, mem = pool(x)
    (spikes.sum() + 0.1 * mem.square().sum()).backward()
    for grad in (pool.weight.grad, pool.mutual_inhibition.grad, x.grad):
        assert grad is not None and torch.isfinite(grad).all()
    assert pool.weight.grad.abs() > 0 and x.grad.abs().sum() > 0


def test_state_dict_round_trip_and_device(device, rng):
    source = SpikingPooling(2, tau=7.0, weight=0.45, mutual_inhibition=0.2, threshold=0.8)
    target = SpikingPooling(2, tau=1.0, weight=0.1, threshold=2.0)
    state = source.state_dict()
    assert {"weight", "mutual_inhibition", "neuron.beta", "neuron.threshold"} <= set(state)
    target.load_state_dict(state)
    x = torch.from_numpy(rng.integers(0, 2, size=(12, 2, 2, 4, 4))).float()
    expected, expected_mem = source(x)
    spikes, mem = target.to(device)(x.to(device))
    assert spikes.device.type == device.type
    assert torch.equal(spikes.cpu(), expected) and torch.equal(mem.cpu(), expected_mem)
    learnable = SpikingPooling(2, beta=0.5, learnable=True)
    learnable.load_state_dict(SpikingPooling(2, beta=0.5, weight=0.9).state_dict())
    assert learnable.weight.item() == pytest.approx(0.9)


def test_empty_time_axis_returns_the_state():
    pool = SpikingPooling(2, beta=0.5)
    state = torch.full((3, 2, 2, 2), 0.25)
    spikes, out_state = pool(torch.zeros(0, 3, 2, 4, 3), state)
    assert spikes.shape == (0, 3, 2, 2, 2) and torch.equal(out_state, state)


def test_integer_and_bool_input():
    pool = SpikingPooling(2, beta=1.0, weight=0.6)
    x = torch.zeros(3, 1, 2, 2, 2, dtype=torch.int16)
    x[:, 0, 1, 0, :] = 1
    expected, _ = pool(x.float())
    assert torch.equal(pool(x)[0], expected)
    assert torch.equal(pool(x.bool())[0], expected)


@pytest.mark.slow
def test_compiles_without_graph_breaks(rng):
    if not hasattr(torch, "compile"):
        pytest.skip("torch.compile is unavailable")
    pool = SpikingPooling((2, 3), tau=4.0, weight=0.4, mutual_inhibition=0.1, learnable=True)
    x = torch.from_numpy(rng.integers(0, 2, size=(4, 2, 2, 6, 5))).float()
    expected, expected_mem = pool(x)
    torch._dynamo.reset()
    try:
        # fullgraph=True: a graph break raises; the eager backend keeps the test fast (the
        # default inductor backend compiles the same single graph, in ~15 s).
        compiled = torch.compile(pool, fullgraph=True, backend="eager")
        spikes, mem = compiled(x)
    except RuntimeError as error:  # pragma: no cover - platform without dynamo support
        if "graph break" in str(error).lower():
            raise
        pytest.skip(f"torch.compile unsupported here: {error}")
    assert torch.equal(spikes, expected) and torch.allclose(mem, expected_mem)
    spikes.sum().backward()
    assert torch.isfinite(pool.weight.grad)


def test_extra_repr():
    text = repr(SpikingPooling((2, 3), beta=0.5, weight=0.25, reset_mechanism="zero"))
    assert "factor=(2, 3)" in text and "beta=0.5" in text and "reset_mechanism='zero'" in text


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"factor": 0}, ValueError, "factor must be a positive integer"),
        ({"factor": 2, "tau": 3.0, "beta": 0.5}, ValueError, "not both"),
        ({"factor": 2, "beta": 1.5}, ValueError, r"beta must lie in \[0, 1\]"),
        ({"factor": 2, "tau": 0.0}, ValueError, "tau must be a positive number"),
        ({"factor": 2, "tau": float("nan")}, ValueError, "tau must be a positive number"),
        ({"factor": 2, "dt": -1.0}, ValueError, "dt must be a positive"),
        ({"factor": 2, "threshold": 0}, ValueError, "threshold must be a positive"),
        ({"factor": 2, "weight": "1"}, TypeError, "weight must be a positive number"),
        ({"factor": 2, "mutual_inhibition": -0.1}, ValueError, "mutual_inhibition must be"),
        ({"factor": 2, "reset_mechanism": "reset"}, ValueError, "reset_mechanism must be one"),
        ({"factor": 2, "learnable": 1}, TypeError, "learnable must be a bool"),
    ],
)
def test_bad_settings_raise(kwargs, error, message):
    factor = kwargs.pop("factor")
    with pytest.raises(error, match=message):
        SpikingPooling(factor, **kwargs)


def test_bad_input_shapes_raise():
    pool = SpikingPooling(2)
    with pytest.raises(ValueError, match=r"\(T, B, 2, H, W\)"):
        pool(torch.zeros(3, 2, 4, 4))
    with pytest.raises(ValueError, match=r"\(T, B, 2, H, W\)"):
        pool(torch.zeros(3, 1, 3, 4, 4))
    with pytest.raises(ValueError, match="state must have shape"):
        pool(torch.zeros(3, 1, 2, 4, 4), torch.zeros(1, 2, 3, 3))
    with pytest.raises(ValueError, match=r"\(B, 2, H, W\)"):
        pool.step(torch.zeros(1, 1, 2, 4, 4))


@pytest.mark.parametrize("shape", [(), (2,), (1, 2, 4, 4, 1)])
def test_the_layer_refuses_a_step_of_the_wrong_rank_naming_its_shape(shape):
    layer = SpikingPoolingLayer(2)
    for fresh in (True, False):  # before any step, and holding a membrane
        if not fresh:
            layer(torch.ones(1, 2, 4, 4))
        with pytest.raises(ValueError, match=re.escape(f"(B, 2, H, W), got {shape}")):
            layer(torch.zeros(shape))
    with pytest.raises(TypeError, match="must be a tensor, got list"):
        layer([[0.0]])
    assert layer.mem.shape == (1, 2, 2, 2)  # the refused steps left the membrane alone


def test_discarded_modules_leave_snntorchs_registry():
    import snntorch

    from evdown_torch.models import SpikingClassifier

    gc.collect()
    before = len(snntorch.SpikingNeuron.instances)
    SpikingPooling(2, beta=0.5)
    SpikingPooling(2, beta=0.5).layer()
    SpikingPoolingLayer(2, beta=0.5)
    SpikingClassifier(num_classes=3)
    kept = SpikingPoolingLayer(2, beta=0.5)
    gc.collect()
    assert len(snntorch.SpikingNeuron.instances) == before + 1  # kept's weak handle
    del kept
    gc.collect()
    assert len(snntorch.SpikingNeuron.instances) == before


def test_snntorch_utils_reset_resets_the_layers_beside_leaky(rng):
    import snntorch as snn
    import snntorch.utils

    torch.manual_seed(0)
    net = nn.Sequential(
        SpikingPoolingLayer(2, beta=0.9, weight=0.6),
        nn.Flatten(),
        nn.Linear(2 * 3 * 3, 4),
        snn.Leaky(beta=0.8, init_hidden=True),
    )
    copy_of_net = copy.deepcopy(net)
    x = torch.from_numpy(rng.integers(0, 2, size=(12, 3, 2, 6, 6))).float()  # (T, B, 2, H, W)

    def run(model) -> torch.Tensor:  # the snntorch idiom: one call per time step
        return torch.stack([model(x[k]) for k in range(x.shape[0])])

    with torch.no_grad():
        first = run(net)
        assert net[0].mem.sum() > 0
        carried = run(net)  # without a reset the membrane carries over: other spikes
        assert not torch.equal(first, carried)
        snntorch.utils.reset(net)
        assert net[0].mem is None and not net[3].mem.any()
        assert torch.equal(run(net), first)  # as from a fresh start
        run(copy_of_net)
        snntorch.utils.reset(copy_of_net)  # a copy's layer is reset too (not its Leaky:
        assert copy_of_net[0].mem is None  # snntorch does not register copies of its own)
        pooled = torch.stack([copy_of_net[0](x[k]) for k in range(x.shape[0])])
        assert torch.equal(pooled, copy_of_net[0].pool(x)[0])

    # The functional module keeps no hidden state: a reset changes nothing.
    pool_net = nn.Sequential(SpikingPooling(2, beta=0.9, weight=0.6), snn.Leaky(beta=0.8))
    spikes, mem = pool_net[0](x)
    snntorch.utils.reset(pool_net)
    again, mem_again = pool_net[0](x)
    assert torch.equal(spikes, again) and torch.equal(mem, mem_again)


def test_layer_in_sequential_with_snntorch_trains_and_resets(rng):
    import snntorch as snn

    torch.manual_seed(0)
    net = nn.Sequential(
        SpikingPoolingLayer(2, beta=0.9, weight=0.6, learnable=True),
        nn.Flatten(),
        nn.Linear(2 * 3 * 3, 4),
        snn.Leaky(beta=0.8, init_hidden=True),
    )
    x = torch.from_numpy(rng.integers(0, 2, size=(12, 3, 2, 6, 6))).float()  # (T, B, 2, H, W)
    target = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3)

    def run() -> torch.Tensor:  # the snntorch idiom: one call per time step
        return torch.stack([net(x[k]) for k in range(x.shape[0])])

    # The layer is the module run step by step: same spikes as the whole tensor at once.
    reset_states(net)
    pooled = torch.stack([net[0](x[k]) for k in range(x.shape[0])])
    expected, mem = net[0].pool(x)
    assert torch.equal(pooled, expected) and torch.equal(net[0].mem, mem)
    assert pooled.sum() > 0

    optimizer = torch.optim.SGD(net.parameters(), lr=0.02)
    before = net[2].weight.detach().clone()
    for _ in range(3):
        reset_states(net)
        loss = ((run().mean(0) - target) ** 2).sum()
        optimizer.zero_grad()
        loss.backward()
        assert torch.isfinite(net[0].pool.weight.grad) and net[2].weight.grad.abs().sum() > 0
        optimizer.step()
    assert not torch.equal(net[2].weight, before)

    # Reset: the same input gives the same output; without a reset the state carries over.
    with torch.no_grad():
        reset_states(net)
        first, first_pooled = run(), net[0].mem.clone()
        run()  # the state carries over into a second pass
        reset_states(net)
        assert net[0].mem is None and not net[3].mem.any()
        again = run()
    assert torch.equal(first, again) and torch.equal(net[0].mem, first_pooled)
    layer = net[0]
    layer.reset()
    fresh = [layer(x[k]) for k in range(x.shape[0])]
    continued = [layer(x[k]) for k in range(x.shape[0])]
    assert not all(torch.equal(a, b) for a, b in zip(fresh, continued, strict=True))
    net[0].reset()
    with pytest.raises(ValueError, match="call reset"):
        net[0](x[0])
        net[0](x[0, :2])  # another batch size without a reset


def test_batch_first_both_ways(rng):
    x = torch.from_numpy(rng.integers(0, 2, size=(7, 3, 2, 4, 6))).float()  # (T, B, ...)
    time_first = SpikingPooling(2, tau=5.0, weight=0.4)
    batch_first = SpikingPooling(2, tau=5.0, weight=0.4, batch_first=True)
    spikes, mem = time_first(x)
    spikes_bf, mem_bf = batch_first(x.transpose(0, 1))
    assert spikes_bf.shape == (3, 7, 2, 2, 3) and spikes.sum() > 0
    assert torch.equal(spikes_bf, spikes.transpose(0, 1)) and torch.equal(mem_bf, mem)
    # a single step is (B, 2, H, W) either way
    assert torch.equal(batch_first.step(x[0])[0], time_first.step(x[0])[0])
    with pytest.raises(ValueError, match=r"\(B, T, 2, H, W\), batch first"):
        batch_first(x[0])
    with pytest.raises(ValueError, match=r"\(T, B, 2, H, W\), time first"):
        time_first(x[0])
    assert "batch_first=True" in repr(batch_first)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_through_two_layers(dtype, rng):
    x = torch.from_numpy(rng.integers(0, 2, size=(10, 2, 2, 8, 8))).float()
    settings = {"beta": 0.5, "weight": 0.5}  # exact in half precision

    def two_layers() -> nn.Sequential:
        return nn.Sequential(SpikingPoolingLayer(2, **settings), SpikingPoolingLayer(2, **settings))

    reference, low = two_layers(), two_layers()
    expected = torch.stack([reference(x[k]) for k in range(10)])
    out = torch.stack([low(x[k].to(dtype)) for k in range(10)])
    assert out.dtype == dtype and low[0].mem.dtype == torch.float32
    assert torch.equal(out.float(), expected) and expected.sum() > 0
    spikes, _ = SpikingPooling(2, **settings)(x.to(dtype))
    assert spikes.dtype == dtype
    assert SpikingPooling(2, **settings)(x.bool())[0].dtype == torch.float32


def test_state_dict_records_the_reset_mechanism():
    zero = SpikingPooling(2, beta=0.5, reset_mechanism="zero")
    state = zero.state_dict()
    SpikingPooling(2, beta=0.7, reset_mechanism="zero").load_state_dict(state)
    with pytest.raises(ValueError, match="reset_mechanism='zero', but this module uses 'subtract'"):
        SpikingPooling(2, beta=0.5).load_state_dict(state)
    layer = SpikingPoolingLayer(2, reset_mechanism="none")
    with pytest.raises(ValueError, match="reset_mechanism='none'"):
        SpikingPoolingLayer(2).load_state_dict(layer.state_dict())


def test_models_holding_the_layer_save_and_load_whole(rng):
    import io

    import snntorch as snn
    import snntorch.utils

    from evdown_torch.models._snn import Surrogate

    torch.manual_seed(0)
    net = nn.Sequential(SpikingPoolingLayer(2, tau=5.0, weight=0.6), nn.Flatten(),
                        nn.Linear(2 * 3 * 3, 4),  # snntorch's own Leaky pickles with a
                        snn.Leaky(beta=0.8, init_hidden=True,  # surrogate that pickles
                                  spike_grad=Surrogate(snn.surrogate.ATan, 2.0)))
    x = torch.from_numpy(rng.integers(0, 2, size=(6, 3, 2, 6, 6))).float()
    buffer = io.BytesIO()
    torch.save(net, buffer)  # the whole model, as pickle does (snntorch's atan was a closure)

    def run(model) -> tuple[torch.Tensor, torch.Tensor]:
        """Output spikes and the input's gradient (the default surrogate, ATan, alpha 2)."""
        inp = x.clone().requires_grad_(True)
        out = torch.stack([model(inp[k]) for k in range(6)])
        out.sum().backward()
        return out.detach(), inp.grad

    expected = run(net)
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=False)
    got = run(loaded)
    assert expected[1].abs().sum() > 0
    assert torch.equal(got[0], expected[0]) and torch.equal(got[1], expected[1])
    assert loaded[0].mem is not None
    snntorch.utils.reset(loaded)  # the loaded layer answers snntorch's reset too
    assert loaded[0].mem is None


def test_spikes_of_another_type_are_a_type_error_naming_it():
    pool = SpikingPooling(2, tau=5.0)
    with pytest.raises(TypeError, match="spikes must be a tensor, got ndarray"):
        pool(np.zeros((3, 1, 2, 4, 4)))
    with pytest.raises(TypeError, match="spikes must be a tensor, got list"):
        pool.current([[0.0]])
    with pytest.raises(TypeError, match="state must be a tensor or None, got ndarray"):
        pool(torch.zeros(3, 1, 2, 4, 4), np.zeros((1, 2, 2, 2)))
    with pytest.raises(TypeError, match="state must be a tensor or None, got list"):
        pool.step(torch.zeros(1, 2, 4, 4), [0.0])
