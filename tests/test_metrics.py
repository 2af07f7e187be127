"""The paper's metrics against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdown_torch.metrics import entropy, event_metrics, num_events, temporal_density
from tests.helpers import DVS_DTYPE


def binary_entropy(a: float) -> float:
    return 0.0 if a in (0.0, 1.0) else -a * math.log2(a) - (1 - a) * math.log2(1 - a)


def test_hand_computed_metrics():
    # 2x2 sensor, D = 10: pixel (0,0) has 2 ON + 1 OFF, pixel (1,1) one ON.
    ev = np.array(
        [(0, 0, True, 0), (0, 0, True, 4), (0, 0, False, 5), (1, 1, True, 10)], dtype=DVS_DTYPE
    )
    m = event_metrics(ev, (2, 2, 2))
    assert m.num_events == 4 == num_events(ev)
    assert m.density == pytest.approx((3 / 10 + 1 / 10) / 4)
    expected = (binary_entropy(0.2) + binary_entropy(0.1) + binary_entropy(0.1)) / 8
    assert m.entropy == pytest.approx(expected)
    assert temporal_density(ev, (2, 2, 2)) == m.density and entropy(ev, (2, 2, 2)) == m.entropy


def test_duration_override_and_units():
    ev = torch.tensor([[0, 0, 100, 1]])
    assert temporal_density(ev, (1, 1, 2), duration=1000) == pytest.approx(1e-3)
    with pytest.raises(ValueError, match="spans no time"):
        temporal_density(ev, (1, 1, 2))
    with pytest.raises(ValueError, match="duration"):
        temporal_density(ev, (1, 1, 2), duration=0)


def test_probability_is_capped_at_one():
    ev = torch.tensor([[0, 0, 0, 1]] * 5 + [[0, 0, 2, 0]])
    m = event_metrics(ev, (1, 1, 2))
    assert m.density == pytest.approx(3.0)
    assert m.entropy == pytest.approx((0.0 + binary_entropy(0.5)) / 2)


def test_empty_stream_has_zero_metrics():
    m = event_metrics(np.empty(0, dtype=DVS_DTYPE), (4, 4, 2))
    assert (m.num_events, m.density, m.entropy) == (0, 0.0, 0.0)


def test_metrics_check_their_inputs():
    with pytest.raises(ValueError, match="x must lie"):
        event_metrics(torch.tensor([[4, 0, 0, 1], [0, 0, 1, 1]]), (4, 4, 2))
    with pytest.raises(TypeError, match="sensor_size"):
        event_metrics(torch.tensor([[0, 0, 0, 1]]), (4, 4))
