"""The method protocol: every transform is its settings plus init_state/step/finish kernels,
and its fast paths (whole stream, stacked batch) equal what the protocol gives."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import evdown_torch as ev
from evdown_torch.collate import EventBatch
from evdown_torch.events import to_events
from evdown_torch.transforms.functional.protocol import Method, run_protocol
from evdown_torch.transforms.functional.settings import RegionSettings, ThresholdSettings
from tests.helpers import random_stream, streaming_cases

SENSOR = (9, 7, 2)

#: The table of instances (tests/helpers.py) that stream through the protocol's kernels.
METHODS = streaming_cases(SENSOR, (3, 2), step=7)


def _same(a: ev.Events, b: ev.Events) -> bool:
    return all(torch.equal(u, v) for u, v in zip(a, b, strict=True))


@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_method_is_three_kernels(name):
    method = METHODS[name].kernels
    assert isinstance(method, Method)
    assert callable(method.init_state) and callable(method.step) and callable(method.finish)


@pytest.mark.parametrize("name", sorted(METHODS))
@pytest.mark.parametrize("seed", range(4))
def test_the_whole_stream_fast_path_equals_the_protocol(name, seed):
    transform = METHODS[name]
    rng = np.random.default_rng(seed)
    arr = random_stream(rng, int(rng.integers(1, 120)), SENSOR, t_max=60)
    events, _ = to_events(arr[rng.permutation(len(arr))], SENSOR)  # any order
    if transform.kernels.whole is None:
        pytest.skip("no whole-stream fast path: the call is the protocol itself")
    fast = transform.kernel(events)
    slow = run_protocol(transform.kernels, transform.settings, events)
    assert _same(fast, slow)


@pytest.mark.parametrize("name", sorted(METHODS))
def test_the_stacked_fast_path_equals_one_protocol_run_per_recording(name, rng):
    transform = METHODS[name]
    parts = [to_events(random_stream(rng, n, SENSOR, t_max=40), SENSOR)[0] for n in (5, 0, 30)]
    batch = EventBatch(ev.Events(*(torch.cat(c) for c in zip(*parts, strict=True))),
                       tuple(p.num_events for p in parts))
    out = transform._batch_events(batch)
    expected = [run_protocol(transform.kernels, transform.settings, p)
                for p in parts]
    assert out.lengths == tuple(e.num_events for e in expected)
    for got, want in zip(out.unbind(), expected, strict=True):
        assert _same(got, want)


def test_settings_are_checked_and_normalised_once_in_their_dataclass():
    assert RegionSettings((4, 4, 2), 2).factor == (2, 2)
    assert ThresholdSettings((4, 4, 2), (1, 2), 1).threshold == 1.0
    with pytest.raises(ValueError, match="threshold"):
        ThresholdSettings((4, 4, 2), 2, 0.0)
    with pytest.raises(ValueError, match="factor"):
        RegionSettings((4, 4, 2), 5)
    # A transform's settings are the dataclass its kernels take.
    assert ev.EventCount((4, 4, 2), 2, threshold=0.5).settings == ThresholdSettings((4, 4, 2),
                                                                                  (2, 2), 0.5)


def test_a_chain_batch_equals_its_calls_and_checks_every_stage(rng):
    chain = ev.Chain(ev.TemporalFunnelling(dt=5), ev.EventCount(SENSOR, factor=2, threshold=0.5))
    recordings = [random_stream(rng, n, SENSOR, t_max=50) for n in (7, 0, 40)]
    for got, one in zip(chain.batch(recordings), recordings, strict=True):
        np.testing.assert_array_equal(got, chain(one))
    too_small = ev.Chain(ev.Downsample(SENSOR, factor=1), ev.EventCount((2, 2, 2), factor=1))
    with pytest.raises(ValueError):
        too_small.batch([random_stream(rng, 20, SENSOR)])
