"""The paper's metrics against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdown_torch.evaluation.metrics import entropy, event_metrics, num_events, temporal_density
from tests.helpers import DVS_DTYPE, random_stream


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


def _dense_consistency(a, b, sensor, bin_width, t0, t1):
    """Slow reference: dense count tensors over the window."""
    w, h, _ = sensor
    bins = int((t1 - t0) // bin_width) + 1
    counts = np.zeros((2, bins, 2, h, w))
    for k, stream in enumerate((a, b)):
        for x, y, p, t in zip(stream["x"], stream["y"], stream["p"], stream["t"]):
            if t0 <= t <= t1:
                counts[k, (t - t0) // bin_width, int(p), y, x] += 1
    total = counts.sum()
    return 1.0 if total == 0 else 1.0 - np.abs(counts[0] - counts[1]).sum() / total


def test_optical_consistency_against_a_dense_reference():
    from evdown_torch.evaluation.metrics import optical_consistency

    rng = np.random.default_rng(7)
    sensor = (5, 4, 2)
    for n_a, n_b in ((300, 200), (50, 400), (0, 10), (0, 0)):
        a = random_stream(rng, n_a, sensor, t_max=1_000)
        b = random_stream(rng, n_b, sensor, t_max=1_000)
        got = optical_consistency(a, b, sensor, bin_width=100, t_start=100, t_end=900)
        assert got == pytest.approx(_dense_consistency(a, b, sensor, 100, 100, 900))
    same = random_stream(rng, 100, sensor, t_max=1_000)
    assert optical_consistency(same, same, sensor, bin_width=50, t_start=0, t_end=999) == 1.0
    # rate-sensitive: every count doubled scores 2/3, unlike a cosine
    doubled = np.concatenate([same, same])
    assert optical_consistency(doubled, same, sensor, bin_width=50, t_start=0,
                               t_end=999) == pytest.approx(2 / 3)
    with pytest.raises(ValueError, match="t_end must not be before"):
        optical_consistency(same, same, sensor, t_start=10, t_end=0)
