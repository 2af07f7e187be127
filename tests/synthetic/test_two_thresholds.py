"""The reference rule with separate ON and OFF thresholds against a slow per-sample loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch.synthetic.two_thresholds import (
    PixelSamples,
    two_threshold_counts,
    two_threshold_crossings,
    two_threshold_level,
)


def level(base, a, b, on, off):
    t = torch.tensor
    return float(two_threshold_level(t(base, dtype=torch.float64), t(a), t(b),
                                      t(on, dtype=torch.float64), t(off, dtype=torch.float64)))


def slow_counts(value, first, base, on, off, a0, b0):
    """Obviously sequential: each segment fires while its end reaches the next level."""
    a_out, b_out, events = [], [], []
    a = b = 0
    for k in range(len(value)):
        if first[k]:
            a, b = a0[k], b0[k]
        elif value[k] > value[k - 1]:
            while level(base[k], a + 1, b, on[k], off[k]) <= value[k]:
                a += 1
                events.append((k, level(base[k], a, b, on[k], off[k]), True))
        elif value[k] < value[k - 1]:
            while level(base[k], a, b + 1, on[k], off[k]) >= value[k]:
                b += 1
                events.append((k, level(base[k], a, b, on[k], off[k]), False))
        a_out.append(a)
        b_out.append(b)
    return a_out, b_out, events


def random_pixels(rng, n_pixels, per_pixel, flat_share=0.1):
    counts = rng.integers(1, per_pixel, n_pixels)
    first = np.concatenate([[True] + [False] * (c - 1) for c in counts])
    steps = rng.normal(0, 0.25, first.size) * (rng.random(first.size) > flat_share)
    value = np.zeros(first.size)
    start = 0
    on_p = rng.uniform(0.05, 0.4, n_pixels)
    off_p = rng.uniform(0.05, 0.4, n_pixels)
    base, on, off, a0, b0 = (np.zeros(first.size) for _ in range(5))
    for p, c in enumerate(counts):
        seg = slice(start, start + c)
        value[seg] = rng.normal(0, 1) + np.cumsum(steps[seg])
        on[seg], off[seg] = on_p[p], off_p[p]
        a0[seg], b0[seg] = rng.integers(0, 5), rng.integers(0, 5)
        # a starting reference inside the window around the first value
        ref = value[start] - rng.uniform(-off_p[p], on_p[p])
        base[seg] = ref - a0[start] * on_p[p] + b0[start] * off_p[p]
        start += c
    return value, first, base, on, off, a0.astype(np.int64), b0.astype(np.int64)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_thresholds_match_the_slow_loop(seed):
    rng = np.random.default_rng(seed)
    value, first, base, on, off, a0, b0 = random_pixels(rng, 60, 80)
    t = torch.from_numpy
    samples = PixelSamples(t(value), t(first), t(base), t(on), t(off))
    a, b = two_threshold_counts(samples, t(a0), t(b0))
    ea, eb, events = slow_counts(value.tolist(), first.tolist(), base.tolist(), on.tolist(),
                                 off.tolist(), a0.tolist(), b0.tolist())
    assert a.tolist() == ea and b.tolist() == eb
    segment, lvl, is_on = two_threshold_crossings(samples, a, b)
    got = list(zip(segment.tolist(), lvl.tolist(), is_on.tolist(), strict=True))
    assert len(events) > 300 and sum(1 for e in events if e[2]) > 100
    assert got == events


def test_two_thresholds_hand_computed_reversal():
    # ON 0.3, OFF 0.1, reference at 0. Up to 0.65: ON at 0.3, 0.6. Down to 0.35: OFF at 0.5,
    # 0.4 (the reference 0.6 minus one and two OFF thresholds). Up to 0.75: the next ON needs
    # 0.4 + 0.3 = 0.7, reached; a one-threshold pixel (0.3) would need 0.9.
    value = torch.tensor([0.0, 0.65, 0.35, 0.75], dtype=torch.float64)
    first = torch.tensor([True, False, False, False])
    full = torch.full_like(value, 1.0)
    zero = torch.zeros(4, dtype=torch.int64)
    samples = PixelSamples(value, first, 0 * full, 0.3 * full, 0.1 * full)
    a, b = two_threshold_counts(samples, zero, zero)
    assert a.tolist() == [0, 2, 2, 3] and b.tolist() == [0, 0, 2, 2]
    seg, lvl, on = two_threshold_crossings(samples, a, b)
    assert seg.tolist() == [1, 1, 2, 2, 3] and on.tolist() == [True, True, False, False, True]
    torch.testing.assert_close(lvl, torch.tensor([0.3, 0.6, 0.5, 0.4, 0.7],
                                                 dtype=torch.float64))


def test_equal_thresholds_agree_with_the_one_threshold_rule():
    from evdown_torch.transforms.functional.reference import reference_index

    rng = np.random.default_rng(5)
    value = np.cumsum(rng.normal(0, 0.7, 400))  # in threshold units, theta = 1
    value[0] = 0.0
    first = np.zeros(400, dtype=bool)
    first[0] = True
    t = torch.from_numpy
    ones = torch.ones(400, dtype=torch.float64)
    zero = torch.zeros(400, dtype=torch.int64)
    a, b = two_threshold_counts(PixelSamples(t(value), t(first), 0 * ones, ones, ones), zero, zero)
    u = t(value)
    q = reference_index(torch.floor(u).long(), u == torch.floor(u), t(first), torch.tensor(0))
    assert (a - b).tolist() == q.tolist()


def test_empty_input():
    e = torch.empty(0, dtype=torch.float64)
    ei = torch.empty(0, dtype=torch.int64)
    a, b = two_threshold_counts(PixelSamples(e, ei.bool(), e, e, e), ei, ei)
    assert a.numel() == b.numel() == 0
